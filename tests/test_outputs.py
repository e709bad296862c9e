"""Outputs (mmgp.data.outputs): complete or absent, never over an input, one writer at a time,
leftovers of killed runs cleaned, unwritable places refused with one InputError."""
from __future__ import annotations

import contextlib
import errno
import hashlib
import json
import os
import shutil
import signal
import socket
import stat
import subprocess
import sys
import tempfile
import textwrap
import time
from pathlib import Path

import numpy as np
import pandas as pd
import pyarrow.parquet as pq
import pytest

from mmgp.data.logs import write_log
from mmgp.data.outputs import (atomic_output_dir, atomic_output_file, atomic_write_bytes, check_output,
                               clean_leftovers, write_table)
from mmgp.errors import InputError

REPO = Path(__file__).resolve().parents[1]
HOST = "".join(c if c.isalnum() or c == "-" else "-" for c in socket.gethostname())[:40]


def digest(path: Path) -> str:
    return hashlib.sha256(path.read_bytes()).hexdigest()


# ---------------------------------------------------------------------------------------------
# Atomic outputs
# ---------------------------------------------------------------------------------------------

def entries(folder: Path) -> list[str]:
    return sorted(x.name for x in folder.iterdir())


def test_atomic_dir_success(tmp_path):
    out = tmp_path / "out"
    with atomic_output_dir(out) as d:
        assert d != out and not out.exists()
        (d / "a.txt").write_text("hello")
    assert (out / "a.txt").read_text() == "hello"
    assert entries(tmp_path) == ["out"]


def test_atomic_dir_failure_leaves_nothing(tmp_path):
    out = tmp_path / "out"
    with pytest.raises(RuntimeError):
        with atomic_output_dir(out) as d:
            (d / "a.txt").write_text("partial")
            raise RuntimeError("boom")
    assert entries(tmp_path) == []


def test_atomic_dir_keyboard_interrupt_leaves_nothing(tmp_path):
    out = tmp_path / "out"
    with pytest.raises(KeyboardInterrupt):
        with atomic_output_dir(out) as d:
            (d / "a.txt").write_text("partial")
            raise KeyboardInterrupt
    assert entries(tmp_path) == []


def test_atomic_dir_refuses_non_empty_without_force(tmp_path):
    out = tmp_path / "out"
    out.mkdir()
    (out / "old.txt").write_text("old")
    entered = []
    with pytest.raises(InputError) as info:
        with atomic_output_dir(out):
            entered.append(1)
    assert not entered
    assert str(out) in str(info.value)
    assert entries(out) == ["old.txt"] and (out / "old.txt").read_text() == "old"
    assert entries(tmp_path) == ["out"]


def test_atomic_dir_accepts_empty_existing(tmp_path):
    out = tmp_path / "out"
    out.mkdir()
    with atomic_output_dir(out) as d:
        (d / "new.txt").write_text("new")
    assert entries(out) == ["new.txt"]
    assert entries(tmp_path) == ["out"]


def test_atomic_dir_refuses_file(tmp_path):
    out = tmp_path / "out"
    out.write_text("x")
    with pytest.raises(InputError):
        with atomic_output_dir(out, force=True):
            pass
    assert out.read_text() == "x"


def test_atomic_dir_force_replaces_only_on_success(tmp_path):
    out = tmp_path / "out"
    out.mkdir()
    (out / "old.txt").write_text("old")
    (out / "sub").mkdir()
    (out / "sub" / "deep.txt").write_text("deep")
    with pytest.raises(ValueError):
        with atomic_output_dir(out, force=True) as d:
            (d / "new.txt").write_text("new")
            raise ValueError("fails half-way")
    assert entries(out) == ["old.txt", "sub"]
    assert (out / "sub" / "deep.txt").read_text() == "deep"
    assert entries(tmp_path) == ["out"]
    with atomic_output_dir(out, force=True) as d:
        (d / "new.txt").write_text("new")
        assert (out / "old.txt").exists()  # old content stays until the new one is complete
    assert entries(out) == ["new.txt"]
    assert entries(tmp_path) == ["out"]


@pytest.fixture
def umask022():
    old = os.umask(0o022)
    yield
    os.umask(old)


def test_output_modes_under_umask_022(tmp_path, umask022):
    out = tmp_path / "out"
    with atomic_output_dir(out) as d:
        write_table(d / "labels.parquet", pd.DataFrame({"t": [0.0, 1.0]}), metadata={"k": "v"})
        write_table(d / "table.csv", pd.DataFrame({"t": [0.0, 1.0]}))
        atomic_write_bytes(d / "report.json", b"{}")
        (d / "plain.txt").write_text("x")
    assert stat.S_IMODE(out.stat().st_mode) == 0o755
    for name in ("labels.parquet", "table.csv", "report.json", "plain.txt"):
        assert stat.S_IMODE((out / name).stat().st_mode) == 0o644, name
    assert entries(out) == ["labels.parquet", "plain.txt", "report.json", "table.csv"]
    assert pq.read_schema(out / "labels.parquet").metadata[b"k"] == b"v"


def test_write_log_mode_under_umask_022(tmp_path, umask022):
    p = write_log(tmp_path / "log.parquet", np.arange(12.0), np.zeros((12, 1)), np.zeros((12, 1)))
    assert stat.S_IMODE(p.stat().st_mode) == 0o644


# ---------------------------------------------------------------------------------------------
# Issue 13: odd CSV dialects, duplicated columns, clock jumps, encodings
# ---------------------------------------------------------------------------------------------


# ---------------------------------------------------------------------------------------------
# Issue 13: an output never replaces, contains or lies inside an input
# ---------------------------------------------------------------------------------------------

def make_input(folder: Path, name: str = "log.parquet") -> Path:
    folder.mkdir(parents=True, exist_ok=True)
    p = folder / name
    write_log(p, np.arange(12.0), np.zeros((12, 1)), np.ones((12, 1)))
    return p


def refused_dir(out, inputs, contains: str) -> None:
    entered = []
    with pytest.raises(InputError, match=contains) as info:
        with atomic_output_dir(out, force=True, inputs=inputs):
            entered.append(1)
    assert not entered
    assert info.value.file == str(out)


def test_out_folder_containing_the_input_log(tmp_path):
    # mmgp train selfdir/log.parquet --out selfdir --force deleted the log
    log = make_input(tmp_path / "selfdir")
    before = digest(log)
    refused_dir(tmp_path / "selfdir", [log], "contains the input")
    assert digest(log) == before and entries(tmp_path / "selfdir") == ["log.parquet"]


def test_out_folder_containing_the_input_through_other_spellings(tmp_path, monkeypatch):
    log = make_input(tmp_path / "data" / "deep")
    (tmp_path / "link").symlink_to(tmp_path / "data")
    monkeypatch.chdir(tmp_path)
    refused_dir(Path("link"), [log], "contains the input")
    refused_dir(Path("data/deep/.."), ["link/deep/log.parquet"], "contains the input")
    assert entries(tmp_path / "data" / "deep") == ["log.parquet"]


def test_out_folder_is_or_lies_inside_an_input_folder(tmp_path):
    model = tmp_path / "model"
    make_input(model, "model.json")
    refused_dir(model, [model], "is the input")
    refused_dir(model / "sub", [model], "lies inside the input folder")
    assert entries(model) == ["model.json"]


def test_out_folder_beside_the_input_is_fine(tmp_path):
    log = make_input(tmp_path / "data")
    with atomic_output_dir(tmp_path / "out", inputs=[log, tmp_path / "missing.csv"]) as d:
        (d / "a").write_text("a")
    assert entries(tmp_path / "out") == ["a"]


@pytest.mark.parametrize("spelling", ["same", "relative", "symlink", "hardlink"])
def test_file_output_equal_to_the_input(tmp_path, monkeypatch, spelling):
    # mmgp predict base s.parquet --out s.parquet --force overwrote the input
    log = make_input(tmp_path)
    before = digest(log)
    out = {"same": log, "relative": Path("./log.parquet"), "symlink": tmp_path / "s.parquet",
           "hardlink": tmp_path / "h.parquet"}[spelling]
    if spelling == "symlink":
        out.symlink_to(log)
    if spelling == "hardlink":
        os.link(log, out)
    monkeypatch.chdir(tmp_path)
    with pytest.raises(InputError, match="is the input"):
        write_table(out, pd.DataFrame({"t": [1.0]}), force=True, inputs=[log])
    with pytest.raises(InputError, match="is the input"):
        atomic_write_bytes(out, b"x", inputs=[str(log)])
    assert digest(log) == before


def test_check_output_refuses_before_any_work(tmp_path):
    (tmp_path / "f").write_text("x")
    (tmp_path / "d").mkdir()
    (tmp_path / "d" / "x").write_text("x")
    with pytest.raises(InputError, match="exists"):
        check_output(tmp_path / "f")
    with pytest.raises(InputError, match="is a folder"):
        check_output(tmp_path / "d", force=True)
    with pytest.raises(InputError, match="not empty"):
        check_output(tmp_path / "d", folder=True)
    with pytest.raises(InputError, match="is a file, not a folder"):
        check_output(tmp_path / "f" / "out", folder=True)
    assert check_output(tmp_path / "f", force=True) == tmp_path / "f"
    assert check_output(tmp_path / "new" / "deeper", folder=True) == tmp_path / "new" / "deeper"
    assert entries(tmp_path) == ["d", "f"]


def test_file_writer_without_force_refuses_an_existing_file(tmp_path):
    p = tmp_path / "pred.parquet"
    p.write_bytes(b"old")
    with pytest.raises(InputError, match="use --force"):
        write_table(p, pd.DataFrame({"t": [1.0]}), force=False)
    assert p.read_bytes() == b"old" and entries(tmp_path) == ["pred.parquet"]


def test_atomic_output_file_keeps_the_suffix_for_format_choosing_writers(tmp_path):
    out = tmp_path / "comp.npz"
    with atomic_output_file(out) as tmp:
        assert tmp.suffix == ".npz" and tmp.parent == tmp_path
        np.savez(tmp, a=np.arange(3))  # numpy appends .npz to any other name
    np.testing.assert_array_equal(np.load(out)["a"], np.arange(3))
    assert entries(tmp_path) == ["comp.npz"]
    with pytest.raises(ZeroDivisionError):
        with atomic_output_file(out, force=True) as tmp:
            tmp.write_bytes(b"half")
            1 / 0
    np.testing.assert_array_equal(np.load(out)["a"], np.arange(3))
    assert entries(tmp_path) == ["comp.npz"]


# ---------------------------------------------------------------------------------------------
# Issue 13: one writer per output; killed runs' leftovers
# ---------------------------------------------------------------------------------------------

WRITER = textwrap.dedent('''
    import os, signal, sys, time
    from pathlib import Path
    from mmgp.data.outputs import atomic_output_dir
    out, ready, action = Path(sys.argv[1]), Path(sys.argv[2]), sys.argv[3]
    with atomic_output_dir(out) as d:
        (d / "who.txt").write_text("first")
        ready.write_text(str(os.getpid()))
        if action == "wait":
            while not Path(sys.argv[4]).exists():
                time.sleep(0.01)
        else:
            os.kill(os.getpid(), getattr(signal, action))
            time.sleep(60)
''')


def start_writer(out: Path, tmp_path: Path, action: str) -> tuple[subprocess.Popen, Path]:
    ready, release = tmp_path / "ready", tmp_path / "release"
    env = dict(os.environ, PYTHONPATH=str(REPO), OMP_NUM_THREADS="1")
    proc = subprocess.Popen([sys.executable, "-c", WRITER, str(out), str(ready), action, str(release)],
                            env=env, stderr=subprocess.PIPE)
    deadline = time.monotonic() + 120
    while not ready.exists() and proc.poll() is None and time.monotonic() < deadline:
        time.sleep(0.01)
    assert ready.exists() or proc.returncode is not None, "writer did not start"
    return proc, release


def test_second_writer_to_the_same_out_is_refused(tmp_path):
    out = tmp_path / "work" / "model"
    proc, release = start_writer(out, tmp_path, "wait")
    try:
        with pytest.raises(InputError, match=rf"another run \(pid {proc.pid} on host") as info:
            with atomic_output_dir(out, force=True) as d:
                (d / "who.txt").write_text("second")
        assert info.value.file == str(out)
        with pytest.raises(InputError, match="another run"):
            write_table(out, pd.DataFrame({"t": [1.0]}))
    finally:
        release.write_text("go")
        proc.wait(timeout=120)
    assert proc.returncode == 0, proc.stderr.read()
    assert (out / "who.txt").read_text() == "first"
    assert entries(out.parent) == ["model"]  # no lock file, no partial folder
    with atomic_output_dir(out, force=True) as d:  # the lock is free again
        (d / "who.txt").write_text("third")
    assert (out / "who.txt").read_text() == "third"


def test_same_process_second_writer_is_refused(tmp_path):
    out = tmp_path / "pred.parquet"
    with atomic_output_file(out) as tmp:
        tmp.write_bytes(b"first")
        with pytest.raises(InputError, match="another run"):
            atomic_write_bytes(out, b"second", force=True)
    assert out.read_bytes() == b"first"
    assert entries(tmp_path) == ["pred.parquet"]


def test_out_filled_by_another_program_meanwhile(tmp_path):
    out = tmp_path / "out"
    with pytest.raises(InputError, match="meanwhile"):
        with atomic_output_dir(out) as d:
            (d / "mine.txt").write_text("mine")
            out.mkdir()
            (out / "theirs.txt").write_text("theirs")
    assert entries(out) == ["theirs.txt"] and entries(tmp_path) == ["out"]
    p = tmp_path / "p.bin"
    with pytest.raises(InputError, match="meanwhile"):
        with atomic_output_file(p) as tmp:
            tmp.write_bytes(b"mine")
            p.write_bytes(b"theirs")
    assert p.read_bytes() == b"theirs" and entries(tmp_path) == ["out", "p.bin"]


@pytest.mark.parametrize("sig", ["SIGKILL", "SIGTERM"])
def test_leftovers_of_a_killed_run_are_removed_by_the_next_run(tmp_path, sig):
    out = tmp_path / "work" / "model"
    proc, _ = start_writer(out, tmp_path, sig)
    proc.wait(timeout=120)
    assert proc.returncode == -getattr(signal, sig)
    left = [n for n in entries(out.parent) if n.startswith(".model.partial.")]
    assert len(left) == 1 and f".{HOST}.{proc.pid}." in left[0]
    with atomic_output_dir(out) as d:
        (d / "who.txt").write_text("next")
    assert entries(out.parent) == ["model"]
    assert entries(out) == ["who.txt"]


def dead_pid() -> int:
    proc = subprocess.Popen([sys.executable, "-c", "pass"])
    proc.wait()
    return proc.pid


def test_only_dead_owners_leftovers_on_this_host_are_removed(tmp_path):
    out = tmp_path / "model"
    dead, live = dead_pid(), os.getpid()
    names = {f".model.partial.{HOST}.{dead}.abc": True, f".model.old.{HOST}.{dead}.def": True,
             f".model.partial.{HOST}.{dead}.xyz.npz": True, f".model.partial.{HOST}.{live}.ghi": False,
             f".model.partial.otherhost.{dead}.jkl": False, ".model.partial.k2j4h1": False,
             f".modelx.partial.{HOST}.{dead}.mno": False}
    for name in names:
        if name.endswith(".npz"):
            (tmp_path / name).write_bytes(b"x")
        else:
            (tmp_path / name / "old").mkdir(parents=True)
            (tmp_path / name / "old" / "f").write_text("x")
    removed = clean_leftovers(out)
    assert sorted(p.name for p in removed) == sorted(n for n, gone in names.items() if gone)
    assert entries(tmp_path) == sorted(n for n, gone in names.items() if not gone)


# ---------------------------------------------------------------------------------------------
# Issue 13: unwritable places give an InputError, not a PermissionError traceback
# ---------------------------------------------------------------------------------------------

@contextlib.contextmanager
def unprivileged():
    """Run the block as a user that file permissions apply to (root ignores them)."""
    if os.geteuid() != 0:
        yield
        return
    os.setegid(65534)
    os.seteuid(65534)
    try:
        yield
    finally:
        os.seteuid(0)
        os.setegid(0)


@pytest.fixture
def shared_dir():
    """A folder outside pytest's owner-only tmp tree, so that an unprivileged user can reach it."""
    base = Path(tempfile.mkdtemp(prefix="mmgp-out-test-"))
    os.chmod(base, 0o755)
    yield base
    for p in [base, *base.rglob("*")]:
        if p.is_dir() and not p.is_symlink():
            os.chmod(p, 0o755)
    shutil.rmtree(base)


def test_read_only_location(shared_dir):
    ro = shared_dir / "ro"
    ro.mkdir()
    os.chmod(ro, 0o555)
    cases = [lambda: atomic_output_dir(ro / "out").__enter__(),
             lambda: atomic_output_dir(ro / "deeper" / "out").__enter__(),
             lambda: write_table(ro / "p.parquet", pd.DataFrame({"t": [1.0]})),
             lambda: atomic_write_bytes(ro / "r.json", b"{}")]
    for case in cases:
        with unprivileged(), pytest.raises(InputError, match="not writable") as info:
            case()
        assert info.value.file.startswith(str(ro))
    assert entries(ro) == []


def test_read_only_existing_out_with_force(shared_dir):
    os.chmod(shared_dir, 0o777)
    out = shared_dir / "out"
    out.mkdir()
    (out / "old.txt").write_text("old")
    os.chmod(out, 0o555)
    with unprivileged(), pytest.raises(InputError, match="out") as info:
        with atomic_output_dir(out, force=True) as d:
            (d / "new.txt").write_text("new")
    assert info.value.file == str(out)
    assert entries(shared_dir) == ["out"] and entries(out) == ["old.txt"]


def test_disk_full_while_writing(tmp_path):
    out = tmp_path / "out"
    with pytest.raises(InputError, match="No space left on device"):
        with atomic_output_dir(out) as d:
            (d / "a.txt").write_text("a")
            with open("/dev/full", "wb") as full:
                full.write(b"x" * 10)
    assert entries(tmp_path) == []


def test_other_errors_inside_the_block_pass_through(tmp_path):
    with pytest.raises(FileNotFoundError):
        with atomic_output_dir(tmp_path / "out"):
            (tmp_path / "no-such-input").read_bytes()
    assert entries(tmp_path) == []


def test_failed_swap_keeps_the_old_output(tmp_path, monkeypatch):
    out = tmp_path / "out"
    out.mkdir()
    (out / "old.txt").write_text("old")
    real_replace = os.replace

    def failing_replace(src, dst):
        if ".partial." in str(src):  # moving the new folder into place fails
            raise OSError(errno.EIO, "Input/output error", str(src))
        return real_replace(src, dst)

    monkeypatch.setattr(os, "replace", failing_replace)
    with pytest.raises(InputError, match="Input/output error"):
        with atomic_output_dir(out, force=True) as d:
            (d / "new.txt").write_text("new")
    assert entries(out) == ["old.txt"] and entries(tmp_path) == ["out"]


# ---------------------------------------------------------------------------------------------
# Several files into a folder the caller gives (DiagnosisResult.write)
# ---------------------------------------------------------------------------------------------

def _small_result():
    from mmgp.diagnosis.result import DiagnosisResult

    return DiagnosisResult(findings=[], fit={}, location={}, joint_names=["j0"], info={"n_samples": 3})


def test_diagnosis_write_failing_midway_leaves_the_folder_as_it_was(tmp_path, monkeypatch):
    """findings.json is written, then report.md fails: the folder keeps its old files and
    content, and gets neither the new findings.json nor anything partial, nor leftovers beside."""
    import mmgp.data.outputs as outputs

    out = tmp_path / "diag"
    out.mkdir()
    (out / "findings.json").write_text("old findings")
    (out / "notes.txt").write_text("the user's")
    real, calls = outputs.atomic_write_text, []

    def fail_second(path, text, **kw):
        calls.append(Path(path).name)
        if len(calls) == 2:
            raise OSError(errno.EIO, "disk gone")
        return real(path, text, **kw)

    monkeypatch.setattr(outputs, "atomic_write_text", fail_second)
    with pytest.raises(OSError):
        _small_result().write(out)
    assert calls == ["findings.json", "report.md"]
    assert entries(out) == ["findings.json", "notes.txt"]
    assert (out / "findings.json").read_text() == "old findings"
    assert entries(tmp_path) == ["diag"]


def test_diagnosis_write_replaces_its_files_and_keeps_the_rest(tmp_path):
    out = tmp_path / "diag"
    out.mkdir()
    (out / "findings.json").write_text("old findings")
    (out / "notes.txt").write_text("the user's")
    _small_result().write(out)
    assert entries(out) == ["findings.json", "notes.txt", "report.html", "report.md"]
    assert json.loads((out / "findings.json").read_text())["findings"] == []
    assert (out / "notes.txt").read_text() == "the user's"
    _small_result().write(tmp_path / "new" / "diag")  # a missing folder is created
    assert entries(tmp_path / "new" / "diag") == ["findings.json", "report.html", "report.md"]
    assert entries(tmp_path) == ["diag", "new"]
