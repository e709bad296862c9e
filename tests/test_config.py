"""The one settings loader (mmgp.config) and the shipped settings files."""
from __future__ import annotations

import inspect
from pathlib import Path

import pytest

from mmgp import InputError, MultimodalGP
from mmgp.config import SECTIONS, load_settings, parameter_names, read_sections

ROOT = Path(__file__).resolve().parents[1]


def write(tmp_path, text, name="s.yaml"):
    p = tmp_path / name
    p.write_text(text)
    return p


def test_section_values_with_flags_on_top(tmp_path):
    p = write(tmp_path, "train:\n  n_modes: 2\n  seed: 4\n  stay_prob: null\nexport:\n  max_support: 300\n")
    got = load_settings(p, "train", MultimodalGP, seed=9, device=None)
    assert got == {"n_modes": 2, "seed": 9, "stay_prob": None}     # None flags leave the file's value
    assert load_settings(p, "export", MultimodalGP.to_compensator) == {"max_support": 300}
    assert load_settings(p, "diagnose", MultimodalGP) == {}        # absent section: nothing set
    assert load_settings(None, "train", MultimodalGP, n_modes="auto") == {"n_modes": "auto"}
    est = MultimodalGP(**got)
    assert est.n_modes == 2 and est.seed == 9


def test_unknown_keys_and_sections_are_refused_by_name(tmp_path):
    p = write(tmp_path, "train:\n  n_mode: 2\n")
    with pytest.raises(InputError) as err:
        load_settings(p, "train", MultimodalGP)
    msg = str(err.value)
    assert "'n_mode'" in msg and "did you mean 'n_modes'" in msg and str(p) in msg
    for name in inspect.signature(MultimodalGP.__init__).parameters:
        if name != "self":
            assert name in msg                                        # the known keys are listed
    p = write(tmp_path, "modes: 2\n")                                 # the former flat layout
    with pytest.raises(InputError, match="unknown section 'modes'.*train, diagnose, compare, export"):
        load_settings(p, "train", MultimodalGP)
    p = write(tmp_path, "train: 3\n")
    with pytest.raises(InputError, match="section 'train' must be a mapping"):
        load_settings(p, "train", MultimodalGP)
    with pytest.raises(InputError, match="does not exist"):
        load_settings(tmp_path / "missing.yaml", "train", MultimodalGP)


def test_invalid_yaml_is_one_line_with_the_line_number(tmp_path):
    p = write(tmp_path, "train:\n  n_modes: 2\n  seed: 1\n  device: 'cpu\n")   # unterminated quote, line 4
    with pytest.raises(InputError) as err:
        read_sections(p)
    msg = str(err.value)
    assert "\n" not in msg and str(p) in msg and "line 4" in msg, msg
    p = write(tmp_path, "train:\n\tn_modes: 2\n")                                # a tab, line 2
    with pytest.raises(InputError) as err:
        read_sections(p)
    assert "\n" not in str(err.value) and "line 2" in str(err.value)


def test_parameter_names_of_classes_and_functions():
    def f(self, a, b=1, *args, c=2, **kw):
        return a

    assert parameter_names(f) == ["a", "b", "c"]
    assert parameter_names(MultimodalGP) == sorted(p for p in inspect.signature(MultimodalGP.__init__).parameters
                                                   if p != "self")
    assert SECTIONS == ("train", "diagnose", "compare", "export")


def test_shipped_default_settings_are_the_defaults():
    """configs/default.yaml lists every setting at its default (drift shows here)."""
    sections = read_sections(ROOT / "configs/default.yaml")
    sig = inspect.signature(MultimodalGP.__init__).parameters
    defaults = {k: p.default for k, p in sig.items() if k not in ("self", "progress")}
    assert sections["train"] == defaults
    sig = inspect.signature(MultimodalGP.to_compensator).parameters
    assert sections["export"] == {k: p.default for k, p in sig.items() if k != "self"}
    from mmgp.diagnosis import Diagnoser

    sig = inspect.signature(Diagnoser.__init__).parameters
    objects = ("self", "effects", "selector", "differentiator")     # Python objects, not settings
    assert sections["diagnose"] == {k: p.default for k, p in sig.items() if k not in objects}
    from mmgp.evaluation.compare import compare

    sig = inspect.signature(compare).parameters
    objects = ("log", "robot", "gp_options", "progress")            # the inputs and Python objects
    assert sections["compare"] == {k: p.default for k, p in sig.items() if k not in objects}
    assert set(sections) == {"train", "export", "diagnose", "compare"}
    panda = load_settings(ROOT / "configs/panda_modes.yaml", "train", MultimodalGP)
    assert panda == {"n_modes": 2, "disturbance": True, "semiparametric": "residual"}
