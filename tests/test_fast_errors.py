"""A wrong path, file type or column is refused from the file's header, before a command loads
torch, scikit-learn or Pinocchio (issue 31: "file does not exist" took 8-10 s). The answer is the
one read_log gives (the same checks), exit status 2; what is loaded is read from sys.modules of a
fresh interpreter (timings live in benchmarks/bench_bad_input.py)."""
from __future__ import annotations

import json
import subprocess
import sys

import numpy as np
import pandas as pd
import pytest

from mmgp.data.headers import check_log_header
from mmgp.data.logs import read_log
from mmgp.errors import InputError

PROBE = """
import json, sys
from mmgp.cli import app
try:
    code = app(sys.argv[1:], standalone_mode=False)   # click returns an Exit's status here
except SystemExit as exc:
    code = exc.code
heavy = sorted(m for m in ("torch", "sklearn", "pinocchio", "scipy.optimize") if m in sys.modules)
print(json.dumps({"code": code, "heavy": heavy}))
"""


def _bad_logs(tmp_path):
    no_tau = tmp_path / "no_tau.parquet"
    pd.DataFrame({"t": np.arange(30) * 0.01, "q_0": np.zeros(30)}).to_parquet(no_tau)
    no_t = tmp_path / "no_t.csv"
    no_t.write_text("time,q_0,tau_0\n0,0,0\n")
    return {"missing": tmp_path / "nope.parquet", "no_tau": no_tau, "no_t": no_t,
            "text": tmp_path / "log.json"}


def test_header_check_refuses_as_read_log_does(tmp_path):
    logs = _bad_logs(tmp_path)
    logs["text"].write_text("{}")
    for path in logs.values():
        with pytest.raises(InputError) as full:
            read_log(path)
        with pytest.raises(InputError) as head:
            check_log_header(path)
        assert str(head.value) == str(full.value)


@pytest.mark.parametrize("command", ["train", "diagnose", "compare"])
@pytest.mark.parametrize("case", ["missing", "no_tau"])
def test_bad_log_answers_before_the_heavy_libraries(tmp_path, command, case):
    path = _bad_logs(tmp_path)[case]
    out = subprocess.run([sys.executable, "-c", PROBE, command, str(path), "--out", str(tmp_path / "out")],
                         capture_output=True, text=True, timeout=120)
    result = json.loads(out.stdout.strip().splitlines()[-1])
    assert result == {"code": 2, "heavy": []}
    assert str(path) in out.stderr and not (tmp_path / "out").exists()
