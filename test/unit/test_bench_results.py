"""benchmarks/_results.py: a benchmark's section of benchmarks/RESULTS.md, written alone."""
from __future__ import annotations

from benchmark_modules import load_benchmark

results = load_benchmark('_results')


def test_a_section_is_the_command_then_paragraphs_and_tables(monkeypatch, tmp_path, capsys):
    monkeypatch.setattr(results, 'RESULTS', tmp_path / 'RESULTS.md')
    monkeypatch.setattr(results, 'machine_line', lambda: 'Python 3, torch 2 (1 thread), x86')
    table = ['| a | b |', '|---|---|', '| 1 | 2 |']
    body = results.publish_section('Speed', script='bench_x.py', write=True,
                                   conditions='; 2 busy processes beside',
                                   blocks=['First paragraph.', table, 'Second.', table[:2]])
    assert body == ('`python benchmarks/bench_x.py` (one run; Python 3, torch 2 (1 thread), '
                    'x86; 2 busy processes beside).\n\nFirst paragraph.\n\n| a | b |\n|---|---|\n'
                    '| 1 | 2 |\n\nSecond.\n\n| a | b |\n|---|---|')
    assert capsys.readouterr().out == body + '\n'
    text = (tmp_path / 'RESULTS.md').read_text()
    assert text.startswith(results.HEADER) and text.endswith(f'## Speed\n\n{body}\n')


def test_without_write_the_results_file_is_left_alone(monkeypatch, tmp_path, capsys):
    monkeypatch.setattr(results, 'RESULTS', tmp_path / 'RESULTS.md')
    monkeypatch.setattr(results, 'machine_line', lambda: 'here')
    body = results.publish_section('Speed', script='bench_x.py', blocks=['Text.'], write=False)
    assert body == '`python benchmarks/bench_x.py` (one run; here).\n\nText.'
    assert not (tmp_path / 'RESULTS.md').exists()
    assert capsys.readouterr().out == body + '\n'


def test_the_machine_line_names_the_first_cpu_model(tmp_path):
    cpuinfo = tmp_path / 'cpuinfo'
    cpuinfo.write_text('processor\t: 0\nvendor_id\t: GenuineIntel\ncpu family\t: 6\n'
                       'model\t\t: 167\nmodel name\t: Intel(R) Xeon(R) Processor\n\n'
                       'processor\t: 1\ncpu family\t: 7\nmodel\t\t: 1\nmodel name\t: Other\n')
    assert results.cpu_model(cpuinfo) == ', Intel(R) Xeon(R) Processor (family 6 model 167)'
    cpuinfo.write_text('processor\t: 0\nmodel name\t: Some CPU\n')
    assert results.cpu_model(cpuinfo) == ', Some CPU'
    assert results.cpu_model(tmp_path / 'missing') == ''
