"""docs/SAFETY_FILTER.md "Many obstacles": a params file carries about 6,000 obstacle rows
(two decimals) within its 128 KiB; the 20,000 of the bound go through the obstacles topic."""
from __future__ import annotations

import re

import numpy as np
import pytest
from repo_files import REPO

from rcbf_ros.parameters.rules import MAX_PARAMS_FILE_BYTES, ParamsFileError, read_params_file


def _with_rows(n: int) -> str:
    """config/unicycle.yaml with ``n`` obstacles of two decimals in +-99 m."""
    rng = np.random.default_rng(0)

    def row(values):
        return '[' + ', '.join(f'{v:.2f}' for v in values) + ']'
    return re.sub(r'      x: .*\n      y: .*\n      radius: .*\n',
                  f'      x: {row(rng.uniform(-99, 99, n))}\n'
                  f'      y: {row(rng.uniform(-99, 99, n))}\n'
                  f'      radius: {row(rng.uniform(0.1, 0.9, n))}\n',
                  (REPO / 'config' / 'unicycle.yaml').read_text())


def test_the_documented_rows_fit_a_params_file(tmp_path):
    path = tmp_path / 'rows.yaml'
    path.write_text(_with_rows(6000))
    assert path.stat().st_size <= MAX_PARAMS_FILE_BYTES
    read_params_file(str(path))
    assert len(_with_rows(6600).encode()) > MAX_PARAMS_FILE_BYTES  # "about": within 10 %


def test_the_bound_of_rows_does_not_fit_and_is_refused_naming_the_file(tmp_path):
    path = tmp_path / 'rows.yaml'
    path.write_text(_with_rows(20000))
    with pytest.raises(ParamsFileError) as refused:
        read_params_file(str(path))
    assert str(path) in str(refused.value) and '\n' not in str(refused.value)
