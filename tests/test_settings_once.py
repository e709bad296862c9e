"""The EM's settings are declared once (issue 32): in :class:`mmgp.labelling.settings.EMSettings`.

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
from mmgp.labelling.sem import MultimodalSEM
from mmgp.labelling.settings import EMSettings, em_setting_names


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


def _literal_defaults(root) -> dict:
    """Setting name -> [(file:class, default source)] for every constructor parameter and
    dataclass field under ``root`` whose default is a literal other than None (None says "not
    set": the callee decides)."""
    import collections
    import pathlib

    out = collections.defaultdict(list)
    for path in sorted(pathlib.Path(root).rglob("*.py")):
        tree = ast.parse(path.read_text())
        for cls in (n for n in ast.walk(tree) if isinstance(n, ast.ClassDef)):
            dataclass = any("dataclass" in ast.unparse(d) for d in cls.decorator_list)
            pairs = []
            for item in cls.body:
                if isinstance(item, ast.FunctionDef) and item.name == "__init__":
                    a = item.args
                    pairs += list(zip(a.args[len(a.args) - len(a.defaults):], a.defaults))
                    pairs += [(x, d) for x, d in zip(a.kwonlyargs, a.kw_defaults) if d is not None]
                elif dataclass and isinstance(item, ast.AnnAssign) and item.value is not None:
                    pairs.append((item.target, item.value))
            for target, default in pairs:
                try:
                    value = ast.literal_eval(default)
                except ValueError:
                    continue                              # a reference to the one declaration
                if value is not None:
                    name = getattr(target, "arg", None) or getattr(target, "id", None)
                    out[name].append((f"{path.name}:{cls.name}", ast.unparse(default)))
    return out


#: names two classes declare on purpose, each its own setting: why
OWN_SETTINGS = {
    "seed": "every estimator's own random stream",
    "block_s": "the EM's leave-block-out length for its GPs; a lone GP's is off (0)",
    "n_inducing": "the EM's inducing inputs for its final sparse GP; a lone SparseGP's",
}


def test_no_setting_is_declared_in_two_classes():
    """Across the package, a setting's default value is written in one class; the others that
    take it refer to that declaration (the GPs to ``mmgp.gp.settings.GP_DEFAULTS``, the EM's
    users to ``EMSettings``, the Diagnoser to the selector's)."""
    import pathlib

    declared = _literal_defaults(pathlib.Path(mmgp.__file__).parent)
    twice = {name: where for name, where in declared.items() if len(where) > 1 and name not in OWN_SETTINGS}
    assert not twice, f"declared in more than one class: {twice}"
    # the allowed ones are still declared twice (a stale entry would hide a new duplicate)
    assert all(len(declared[name]) > 1 for name in OWN_SETTINGS)


def test_the_scan_finds_a_setting_declared_twice(tmp_path):
    (tmp_path / "a.py").write_text("class A:\n    def __init__(self, *, tol=0.1, ref=B.x, off=None):\n        pass\n")
    (tmp_path / "b.py").write_text("from dataclasses import dataclass\n@dataclass\nclass B:\n    tol: float = 0.1\n")
    declared = _literal_defaults(tmp_path)
    assert sorted(declared) == ["tol"] and len(declared["tol"]) == 2


def test_the_gps_defaults_are_the_procedures():
    from mmgp.gp.exact import ExactGP
    from mmgp.gp.settings import GP_DEFAULTS
    from mmgp.gp.sparse import SparseGP

    names = [f.name for f in dataclasses.fields(GP_DEFAULTS)]
    for cls in (ExactGP, SparseGP):
        src = _signature_defaults_source(cls)
        assert {n: src[n] for n in names} == {n: f"_GP.{n}" for n in names}, cls
    assert ExactGP()._procedure() == GP_DEFAULTS
