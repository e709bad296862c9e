"""The EM's settings are declared once (issue 32): in :class:`mmgp.models.settings.EMSettings`.

MultimodalSEM declares none of them (it takes an EMSettings and overrides by name);
MultimodalGP's defaults for the settings it exposes are EMSettings' own, read from the source of
its signature (not compared by value: equal literals would still be two declarations); every
exposed setting reaches the EM (each set to a value of its own, enumerated)."""
import ast
import dataclasses
import inspect
import textwrap

import pytest

import mmgp
from mmgp.models.sem import MultimodalSEM
from mmgp.models.settings import EMSettings, em_setting_names


def _signature_defaults_source(cls) -> dict:
    """Parameter name -> the source of its default expression in ``cls.__init__``."""
    tree = ast.parse(textwrap.dedent(inspect.getsource(cls.__init__)))
    args = tree.body[0].args
    pos = args.args[len(args.args) - len(args.defaults):]
    pairs = list(zip(pos, args.defaults)) + [(a, d) for a, d in zip(args.kwonlyargs, args.kw_defaults) if d is not None]
    return {a.arg: ast.unparse(d) for a, d in pairs}


def test_the_em_declares_no_setting_of_its_own():
    params = set(inspect.signature(MultimodalSEM.__init__).parameters) - {"self"}
    assert params == {"n_modes", "settings", "seed", "progress", "overrides"}
    assert not params & set(em_setting_names())


def test_the_estimator_takes_its_em_defaults_from_emsettings():
    defaults = _signature_defaults_source(mmgp.MultimodalGP)
    shared = [name for name in em_setting_names() if name in defaults]
    # the estimator exposes the EM settings a user sets (26 of them); the others are internal
    assert len(shared) == 26
    wrong = {name: defaults[name] for name in shared if defaults[name] != f"_EM.{name}"}
    assert not wrong, f"MultimodalGP declares these EM settings itself: {wrong}"


def test_every_exposed_setting_reaches_the_em():
    est = mmgp.MultimodalGP()
    shared = [name for name in em_setting_names() if name in est.get_params()]
    given = {}
    for i, name in enumerate(shared):
        value = getattr(EMSettings(), name)
        # a value of its own per setting, of the setting's type
        if isinstance(value, bool):
            given[name] = not value
        elif isinstance(value, str):
            given[name] = {"estep": "gibbs", "gp_method": "exact"}[name]
        else:
            given[name] = 1000 + i
    est.set_params(**given)
    settings = est._em_settings(None, {})
    for name, value in given.items():
        assert getattr(settings, name) == value, name
    # the windows shortened for a short log win over the estimator's own
    assert est._em_settings(None, {"exclusion_s": 0.25}).exclusion_s == 0.25


def test_overrides_replace_by_name_and_refuse_unknown_names():
    base = EMSettings(max_sweeps=7)
    sem = MultimodalSEM(2, base, min_sweeps=3)
    assert (sem.settings.max_sweeps, sem.settings.min_sweeps, sem.n_modes) == (7, 3, 2)
    assert base.min_sweeps == EMSettings().min_sweeps          # the given settings are not changed
    with pytest.raises(TypeError):
        MultimodalSEM(1, max_sweep=3)
    with pytest.raises(ValueError):
        MultimodalSEM(1, estep="viterbi")
    with pytest.raises(dataclasses.FrozenInstanceError):
        sem.settings.max_sweeps = 3
