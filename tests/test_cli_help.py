"""``--help`` of every command (issue 31 item 7): flags without ``<bool>``, arguments as ``LOGS...``,
every default shown, a setting's default the shipped default.yaml's (read here independently);
``config show default`` has each command's section; train says when rate_hz thinned the log."""
from __future__ import annotations

import re
from pathlib import Path

import pytest
import typer
import yaml
from typer.testing import CliRunner

from mmgp.cli import app

ROOT = Path(__file__).resolve().parents[1]
DEFAULT_YAML = ROOT / "mmgp/resources/configs/default.yaml"
LOG = ROOT / "mmgp/resources/replica/replica_log.parquet"
runner = CliRunner()
WIDE = {"COLUMNS": "300", "NO_COLOR": "1", "TERM": "dumb"}
ANSI = re.compile(r"\x1b\[[0-9;]*m")

# The options whose default is a setting of the shipped default.yaml: (command, option) -> (section, key)
SETTINGS = {("train", "--modes"): ("train", "n_modes"),
            ("train", "--disturbance"): ("train", "disturbance"),
            ("train", "--device"): ("train", "device"),
            ("train", "--seed"): ("train", "seed"),
            ("export", "--max-support"): ("export", "max_support"),
            ("compare", "--max-train"): ("compare", "max_train")}


def _commands():
    """(command path, click command) of every command, the config group's included."""
    root = typer.main.get_command(app)
    found = []

    def walk(cmd, path):
        subs = getattr(cmd, "commands", None)
        if subs:
            for name, sub in subs.items():
                walk(sub, [*path, name])
        else:
            found.append((path, cmd))

    walk(root, [])
    return found


COMMANDS = _commands()


def _help(path: list[str]) -> str:
    res = runner.invoke(app, [*path, "--help"], env=WIDE)
    assert res.exit_code == 0, res.output
    return ANSI.sub("", res.output)


def _row(text: str, option: str) -> str:
    """The help row of ``option`` (its line in the options panel)."""
    rows = [ln for ln in text.splitlines() if re.search(rf"(^|[\s│]){re.escape(option)}(\s|$)", ln)]
    assert rows, f"{option} not in help:\n{text}"
    return rows[0]


def _shipped() -> dict:
    return yaml.safe_load(DEFAULT_YAML.read_text())


def test_every_command_is_walked():
    names = {" ".join(p) for p, _ in COMMANDS}
    assert {"train", "compare", "diagnose", "fleet", "export", "convert", "annotate", "demo", "version",
            "config show", "config list"} <= names


@pytest.mark.parametrize("path", [p for p, _ in COMMANDS] + [[]], ids=lambda p: " ".join(p) or "mmgp")
def test_help_shows_flags_as_flags_and_plain_argument_names(path):
    text = _help(path)
    assert "<bool>" not in text
    assert not re.search(r"\{\w+\}", text), text          # no {logs}...
    cmd = dict((" ".join(p), c) for p, c in COMMANDS).get(" ".join(path))
    for param in (cmd.params if cmd is not None else []):
        if param.param_type_name == "argument":
            name = param.name.upper() + ("..." if param.nargs != 1 else "")
            assert name in text.splitlines()[1], text.splitlines()[1]    # the usage line


@pytest.mark.parametrize("path", [p for p, _ in COMMANDS], ids=lambda p: " ".join(p))
def test_every_default_is_shown(path):
    text = _help(path)
    cmd = dict((" ".join(p), c) for p, c in COMMANDS)[" ".join(path)]
    shipped = _shipped()
    for param in cmd.params:
        if param.param_type_name != "option" or param.name == "version":
            continue
        option = param.opts[0]
        if (path[-1], option) in SETTINGS:
            section, key = SETTINGS[path[-1], option]
            value = shipped[section][key]
            expected = ("disturbance" if value else "no-disturbance") if isinstance(value, bool) else str(value)
        elif param.default is None or param.is_flag and not param.secondary_opts:
            continue                               # no default (help says what is done), or an off flag
        else:
            expected = str(param.default)
        assert f"[default: {expected}]" in _row(text, option), (option, _row(text, option))


def test_settings_options_cover_every_option_left_to_a_setting():
    """An option of a --config command that defaults to None but names a setting of its section
    shows the shipped value: the table above lists every such option whose shipped value is not null."""
    shipped = _shipped()
    sections = {"train": "train", "export": "export", "diagnose": "diagnose", "compare": "compare"}
    for path, cmd in COMMANDS:
        section = sections.get(path[-1])
        if section is None:
            continue
        for param in cmd.params:
            key = {"modes": "n_modes"}.get(param.name, param.name)
            if param.param_type_name == "option" and param.default is None and shipped[section].get(key) is not None:
                assert (path[-1], param.opts[0]) in SETTINGS, (path, param.opts[0])


def test_config_show_default_has_every_command_section():
    res = runner.invoke(app, ["config", "show", "default"])
    assert res.exit_code == 0, res.output
    tops = re.findall(r"^(\w+):", res.output, flags=re.M)
    assert len(tops) == len(set(tops)), f"a section twice: {tops}"   # YAML would keep the last silently
    with_config = {p[-1] for p, c in COMMANDS if any("--config" in getattr(q, "opts", ()) for q in c.params)}
    assert with_config == {"train", "export", "diagnose", "compare"}
    assert set(yaml.safe_load(res.output)) == with_config


def test_train_says_how_many_samples_rate_hz_kept(tmp_path):
    import pandas as pd

    t = pd.read_parquet(LOG)["t"].to_numpy()
    rate = 10.0
    # a uniform log: one kept sample per 1/rate s tick from the first sample to the last
    n_used = int((t[-1] - t[0]) * rate + 1e-6) + 1
    assert n_used < len(t)
    cfg = tmp_path / "thin.yaml"
    cfg.write_text(f"train:\n  rate_hz: {rate:g}\n")
    res = runner.invoke(app, ["train", str(LOG), "--out", str(tmp_path / "run"), "--config", str(cfg),
                              "--no-disturbance"])
    assert res.exit_code == 0, res.output
    assert f"{n_used:,} of {len(t):,} samples used: rate_hz 10" in res.output
    import json

    rep = json.loads((tmp_path / "run" / "report.json").read_text())
    assert rep["thinning"] == {"rate_hz": rate, "n_read": len(t), "n_used": n_used} and rep["n_samples"] == n_used
    assert len(pd.read_parquet(tmp_path / "run" / "labels.parquet")) == n_used


def test_thinning_line_only_when_samples_were_dropped():
    from mmgp.cli.common import thinning_line

    assert thinning_line(2100, 20544, "rate_hz 100") == "2,100 of 20,544 samples used: rate_hz 100"
    assert thinning_line(330, 330, "rate_hz 100") is None
