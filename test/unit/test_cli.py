"""The ``rcbf_ros`` command: every subcommand reaches its module, its command line unchanged."""
from __future__ import annotations

import importlib
import os
from pathlib import Path
import subprocess
import sys

import pytest
import yaml

from rcbf_ros.cli import interface_doc
from rcbf_ros.cli import main as cli

REPO = Path(__file__).resolve().parents[2]


def test_help_lists_every_subcommand_with_its_line(capsys):
    with pytest.raises(SystemExit) as exit_info:
        cli.main(['--help'])
    assert exit_info.value.code == 0
    out = capsys.readouterr().out
    lines = {**cli.PARSED, **{name: d.help for name, d in cli.DELEGATED.items()}}
    assert set(lines) == {'train', 'experiment', 'bag', 'launch', 'refilter', 'summary',
                          'interface-doc'}
    for name, line in lines.items():
        assert any(row.split() == [name, *line.split()] for row in out.splitlines()), name
    assert 'rcbf_ros_launch' in out and 'rcbf_ros_refilter' in out


@pytest.mark.parametrize('name', sorted(cli.DELEGATED))
def test_a_delegated_subcommand_hands_its_arguments_on_and_returns_the_exit_code(
        name, monkeypatch):
    module = importlib.import_module(cli.DELEGATED[name].module)
    seen: list[list[str]] = []

    def fake_main(argv):
        seen.append(argv)
        return 7

    monkeypatch.setattr(module, 'main', fake_main)
    assert cli.main([name, '--help', 'a:=1', '-p', 'x']) == 7
    assert seen == [['--help', 'a:=1', '-p', 'x']]


def test_launch_shows_a_launchs_arguments(capsys):
    assert cli.main(['launch', 'safety_filter', '--show-args']) == 0
    out = capsys.readouterr().out
    assert out.startswith("Arguments of safety_filter (pass arguments as '<name>:=<value>'):")
    assert "'cmd_in':" in out


def test_refilter_help_is_the_refilter_commands_own(capsys):
    with pytest.raises(SystemExit) as exit_info:
        cli.main(['refilter', '--help'])
    assert exit_info.value.code == 0
    out = capsys.readouterr().out
    assert out.startswith('usage: rcbf_ros refilter') and '--params-file' in out


def test_summary_of_a_missing_directory_is_one_line_and_exit_2(tmp_path, capsys):
    missing = tmp_path / 'no_run'
    assert cli.main(['summary', str(missing)]) == 2
    captured = capsys.readouterr()
    assert captured.out == ''
    assert captured.err == (f'rcbf_ros summary: error: {missing}: no such directory '
                            '(expected a run directory)\n')
    a_file = tmp_path / 'file'
    a_file.write_text('')
    assert cli.main(['summary', str(a_file)]) == 2
    assert 'not a directory' in capsys.readouterr().err


def test_summary_help_prints_the_usage(capsys):
    assert cli.main(['summary', '--help']) == 0
    assert capsys.readouterr().out.startswith('usage: ')


def test_interface_doc_prints_the_generated_section(capsys):
    assert cli.main(['interface-doc']) == 0
    out = capsys.readouterr().out
    assert out.startswith(interface_doc.BEGIN) and interface_doc.END in out


@pytest.mark.parametrize('option', ['--check', '--write'])
@pytest.mark.parametrize(('kind', 'words'), [
    ('fifo', 'not a regular file (a FIFO)'), ('dev_zero', 'not a regular file'),
    ('directory', 'not a regular file (a directory)'), ('oversize', 'larger than'),
    ('not_utf8', 'utf-8'), ('missing', 'No such file')])
@pytest.mark.timeout(60)  # a FIFO read for its text would wait for a writer for good
def test_interface_doc_reads_only_a_document_sized_regular_file(kind, words, option, tmp_path,
                                                               capsys):
    """--check and --write refuse what is no document before reading it whole: exit 2, one
    line naming the path; nothing written."""
    path = {'dev_zero': Path('/dev/zero')}.get(kind, tmp_path / 'doc.md')
    if kind == 'fifo':
        os.mkfifo(path)
    elif kind == 'directory':
        path.mkdir()
    elif kind == 'oversize':  # sparse: the section's markers at its start
        path.write_text(f'{interface_doc.BEGIN}\n{interface_doc.END}\n')
        os.truncate(path, interface_doc.MAX_DOC_BYTES + 1)
    elif kind == 'not_utf8':
        path.write_bytes(f'{interface_doc.BEGIN}\n{interface_doc.END}\n'.encode() + b'\xff')
    before = path.read_bytes() if path.is_file() else None
    assert interface_doc.main([option, str(path)]) == 2
    err = capsys.readouterr().err
    assert len(err.strip().splitlines()) == 1 and str(path) in err, err
    assert words.lower() in err.lower() and 'Traceback' not in err, err
    assert (path.read_bytes() if path.is_file() else None) == before


@pytest.mark.parametrize('name', sorted(cli.PARSED))
def test_the_parsed_subcommands_keep_their_help(name, capsys):
    with pytest.raises(SystemExit) as exit_info:
        cli.main([name, '--help'])
    assert exit_info.value.code == 0
    assert capsys.readouterr().out.startswith(f'usage: rcbf_ros {name} ')


def test_an_unknown_subcommand_is_refused_naming_the_choices(capsys):
    with pytest.raises(SystemExit) as exit_info:
        cli.main(['lanch'])
    assert exit_info.value.code == 2
    err = capsys.readouterr().err
    assert "invalid choice: 'lanch'" in err and "'interface-doc'" in err


def test_python_m_rcbf_ros_summary_as_run_sh_calls_it(tmp_path):
    """scripts/run.sh ends with ``python -m rcbf_ros summary <run>``: no traceback, exit 2."""
    missing = tmp_path / 'never_started'
    done = subprocess.run([sys.executable, '-m', 'rcbf_ros', 'summary', str(missing)],
                          capture_output=True, text=True, cwd=REPO, timeout=120)
    assert done.returncode == 2
    assert done.stderr.splitlines() == [f'rcbf_ros summary: error: {missing}: no such '
                                        'directory (expected a run directory)']
    assert 'python -m rcbf_ros summary "$RUN"' in (REPO / 'scripts' / 'run.sh').read_text()


BAD_TRAIN_ARGUMENTS = [
    ('--seed', '-1'), ('--seed', str(2 ** 32)), ('--seed', str(10 ** 24)),
    ('--initial-alpha', 'inf'), ('--initial-alpha', 'nan'), ('--initial-alpha', '1e308'),
    ('--threads', str(10 ** 21)), ('--threads', '0'), ('--threads', '1025'),
    ('--episodes', str(10 ** 30)), ('--episodes', '0'), ('--start-steps', '-1'),
    ('--update-after', '-1'), ('--batch-size', str(10 ** 21)), ('--batch-size', '0'),
    ('--gp-refit-interval', '0'), ('--max-steps', str(10 ** 21)), ('--max-steps', '0'),
    ('--checkpoint-every', '0'),
]


@pytest.mark.parametrize(('option', 'value'), BAD_TRAIN_ARGUMENTS)
def test_train_refuses_an_out_of_bounds_option_in_one_line(option, value, tmp_path, capsys):
    """Every bound is a declaration of TrainingSettings, checked before the run is planned:
    exit 2, one line naming the option, nothing on stdout, no directory made."""
    out = tmp_path / 'run'
    code = cli.main(['train', '--system', 'unicycle', '--mode', 'unconstrained',
                     '--episodes', '1', '--out', str(out), option, value])
    captured = capsys.readouterr()
    assert code == 2
    assert captured.out == ''
    lines = captured.err.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith(f'error: {option}: '), captured.err
    assert 'Traceback' not in captured.err
    assert not out.exists()


def test_train_refuses_perception_sources_in_one_line(tmp_path, capsys):
    """A config with observation_sources (a node's sensors) is refused before the run starts:
    training has no sensors."""
    params = yaml.safe_load((REPO / 'config' / 'unicycle.yaml').read_text())
    params['/safety_filter']['ros__parameters'].update(
        {'observation_sources': ['front'], 'front.type': 'scan', 'front.topic': '/scan'})
    config = tmp_path / 'sources.yaml'
    config.write_text(yaml.safe_dump(params))
    code = cli.main(['train', '--system', 'unicycle', '--mode', 'unconstrained',
                     '--episodes', '1', '--out', str(tmp_path / 'run'),
                     '--config', str(config)])
    captured = capsys.readouterr()
    assert code == 2
    assert captured.out == ''
    lines = captured.err.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith('error: observation_sources: '), captured.err
