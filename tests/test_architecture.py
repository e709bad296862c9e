"""The layout's rules, read from the code itself (docs/architecture.md draws the picture).

Every import inside the package, module-level or inside a function, is read with ``ast`` and
placed on its layer; an import may point to the same or a lower layer, never back up. The side
package ``mmgp.sim`` (MuJoCo, an optional extra) may use the core; the core never imports it.
Sizes: no module over 600 lines, no function over 80 lines of code (docstring excluded).
"""
from __future__ import annotations

import ast
from pathlib import Path

import pytest

PKG = Path(__file__).resolve().parents[1] / "mmgp"

# Lowest first. A module's layer is that of its longest listed prefix.
LAYERS = {
    "mmgp._version": 1, "mmgp.errors": 1, "mmgp.config": 1, "mmgp.resources": 1, "mmgp.threads": 1,
    "mmgp.progress": 1,
    "mmgp.data": 2,
    "mmgp.gp": 3,
    "mmgp.physics": 4,
    "mmgp.labelling": 5,
    "mmgp.compensator": 6, "mmgp.diagnosis": 6, "mmgp.evaluation": 6, "mmgp.convert": 6,
    "mmgp.estimator": 7, "mmgp.saved_model": 7, "mmgp.fleet": 7,
    "mmgp": 8, "mmgp.cli": 8,
}
SIDE = "mmgp.sim"
MAX_MODULE_LINES = 600
MAX_FUNCTION_LINES = 80


def _modules():
    for path in sorted(PKG.rglob("*.py")):
        parts = list(path.relative_to(PKG.parent).with_suffix("").parts)
        if parts[-1] == "__init__":
            parts = parts[:-1]
        yield ".".join(parts), path


def _layer(module: str) -> int | None:
    if module == SIDE or module.startswith(SIDE + "."):
        return None
    best = max((p for p in LAYERS if module == p or module.startswith(p + ".")), key=len)
    return LAYERS[best]


def _imports(module: str, path: Path):
    """(line, imported module) for every import of an mmgp module in ``path``."""
    is_pkg = path.name == "__init__.py"
    package = module if is_pkg else module.rsplit(".", 1)[0]
    for node in ast.walk(ast.parse(path.read_text())):
        if isinstance(node, ast.ImportFrom):
            if node.level:
                base = package.split(".")
                base = base[:len(base) - (node.level - 1)]
                target = ".".join(base + ([node.module] if node.module else []))
            else:
                target = node.module or ""
            names = [target] if node.module else [f"{target}.{a.name}" for a in node.names]
            for name in names:
                if name.startswith("mmgp"):
                    yield node.lineno, name
        elif isinstance(node, ast.Import):
            for a in node.names:
                if a.name.startswith("mmgp"):
                    yield node.lineno, a.name


def _existing(name: str) -> str:
    """The module an import names: ``mmgp.gp.exact.ExactGP`` -> ``mmgp.gp.exact``."""
    known = {m for m, _ in _modules()}
    while name not in known and "." in name:
        name = name.rsplit(".", 1)[0]
    return name


def test_no_import_runs_back_up_and_core_never_imports_sim():
    bad = []
    for module, path in _modules():
        mine = _layer(module)
        for line, target in _imports(module, path):
            target = _existing(target)
            theirs = _layer(target)
            if mine is None:           # the side package may use the core
                continue
            if theirs is None:
                bad.append(f"{path.name}:{line} {module} imports the side package {target}")
            elif theirs > mine:
                bad.append(f"{path.name}:{line} {module} (layer {mine}) imports {target} (layer {theirs})")
    assert not bad, "imports that run back up:\n" + "\n".join(bad)


def test_the_rule_catches_an_upward_import(tmp_path):
    # The checker itself must be able to fail: a data module importing the CLI is an upward arrow.
    f = tmp_path / "x.py"
    f.write_text("from ..cli import app\n")
    found = [t for _, t in _imports("mmgp.data.x", f)]
    assert found == ["mmgp.cli"] and _layer(_existing(found[0])) > _layer("mmgp.data.x")


def _function_lengths(path: Path):
    tree = ast.parse(path.read_text())
    for node in ast.walk(tree):
        if isinstance(node, (ast.FunctionDef, ast.AsyncFunctionDef)):
            body = node.body
            if body and isinstance(body[0], ast.Expr) and isinstance(getattr(body[0], "value", None), ast.Constant) \
                    and isinstance(body[0].value.value, str):
                body = body[1:]
            if body:
                yield node.name, node.lineno, body[-1].end_lineno - body[0].lineno + 1


def test_modules_and_functions_stay_readable():
    long_modules = [f"{p.relative_to(PKG.parent)}: {n} lines" for _, p in _modules()
                    if (n := len(p.read_text().splitlines())) > MAX_MODULE_LINES]
    long_functions = [f"{p.relative_to(PKG.parent)}:{line} {name}: {n} lines" for m, p in _modules()
                      if _layer(m) is not None for name, line, n in _function_lengths(p) if n > MAX_FUNCTION_LINES]
    assert not long_modules and not long_functions, "\n".join(long_modules + long_functions)


@pytest.mark.parametrize("snippet, expected", [("def f():\n    '''doc'''\n" + "    x = 1\n" * 3, 3)])
def test_function_length_counts_code_not_docstring(tmp_path, snippet, expected):
    f = tmp_path / "m.py"
    f.write_text(snippet)
    assert [n for _, _, n in _function_lengths(f)] == [expected]


def _cycles(edges: dict[str, set[str]]) -> list[list[str]]:
    """Strongly connected components with more than one module (Tarjan), i.e. import circles."""
    index, low, stack, on, out = {}, {}, [], set(), []

    def visit(v):
        index[v] = low[v] = len(index)
        stack.append(v)
        on.add(v)
        for w in edges.get(v, ()):
            if w not in index:
                visit(w)
                low[v] = min(low[v], low[w])
            elif w in on:
                low[v] = min(low[v], index[w])
        if low[v] == index[v]:
            comp = []
            while True:
                w = stack.pop()
                on.discard(w)
                comp.append(w)
                if w == v:
                    break
            if len(comp) > 1:
                out.append(sorted(comp))

    for v in list(edges):
        if v not in index:
            visit(v)
    return out


def test_no_two_modules_import_each_other():
    # Package faces (__init__) only hand names on; circles are looked for between modules.
    faces = {m for m, p in _modules() if p.name == "__init__.py"}
    edges = {m: {t for t in (_existing(x) for _, x in _imports(m, p)) if t != m and t not in faces}
             for m, p in _modules() if m not in faces}
    assert not _cycles(edges), f"import circles: {_cycles(edges)}"
    assert _cycles({"a": {"b"}, "b": {"c"}, "c": {"a"}, "d": {"a"}}) == [["a", "b", "c"]]


# Writing a file is the atomic writer's job (mmgp.data.outputs): complete or absent, never over
# an input. Elsewhere only scratch files in a temporary folder, named here with why.
WRITER = "mmgp.data.outputs"
SCRATCH = {("mmgp.diagnosis.corrected", "write_corrected"),   # the URDF the MJCF builder reads
           ("mmgp.sim.family", "_models"),                     # the URDF MuJoCo loads
           ("mmgp.sim.concealed", "actuator_urdf_path")}       # the same, once per process
_WRITE_METHODS = {"write_text", "write_bytes", "to_parquet", "to_csv", "to_json", "savefig", "save", "savez",
                  "savez_compressed", "savetxt", "dump", "write_table"}


def _direct_writes(path: Path):
    """(function, line, call) of each call in ``path`` that writes a file itself: the methods
    above on something other than an in-memory buffer named ``buf``, and ``open`` for writing."""
    tree = ast.parse(path.read_text())
    owner = {}
    for fn in ast.walk(tree):
        if isinstance(fn, (ast.FunctionDef, ast.AsyncFunctionDef)):
            for node in ast.walk(fn):
                owner.setdefault(id(node), fn.name)
    for node in ast.walk(tree):
        if not isinstance(node, ast.Call):
            continue
        f, args = node.func, node.args
        first = args[0] if args else None
        to_buffer = isinstance(first, ast.Name) and first.id == "buf"
        if isinstance(f, ast.Attribute) and f.attr in _WRITE_METHODS and not to_buffer:
            if f.attr == "save" and not (isinstance(f.value, ast.Name) and f.value.id in ("np", "numpy", "torch")):
                continue  # a model's own save() goes through the writer itself
            if f.attr == "write_table" and not (isinstance(f.value, ast.Name) and f.value.id == "pq"):
                continue  # mmgp.data.outputs.write_table is the writer
            if f.attr in ("to_json", "to_csv") and first is None:
                continue  # without a path they return the text
            if f.attr == "dump" and not (isinstance(f.value, ast.Name) and f.value.id in ("json", "pickle")):
                continue
            yield owner.get(id(node), "<module>"), node.lineno, f.attr
        elif isinstance(f, ast.Name) and f.id == "open":
            mode = args[1] if len(args) > 1 else next((k.value for k in node.keywords if k.arg == "mode"), None)
            if isinstance(mode, ast.Constant) and any(c in str(mode.value) for c in "wax+"):
                yield owner.get(id(node), "<module>"), node.lineno, "open"


def test_outputs_are_written_by_the_atomic_writer_only():
    bad = [f"{p.relative_to(PKG.parent)}:{line} {fn}: {call}(...)" for m, p in _modules() if m != WRITER
           for fn, line, call in _direct_writes(p) if (m, fn) not in SCRATCH]
    assert not bad, "files written outside mmgp.data.outputs:\n" + "\n".join(bad)


def test_the_writer_rule_catches_direct_writes(tmp_path):
    f = tmp_path / "x.py"
    f.write_text("def g(out, fig, df, buf):\n    (out / 'a.json').write_text('{}')\n    fig.savefig(out / 'p.png')\n"
                 "    fig.savefig(buf)\n    df.to_parquet(out)\n    open(out, 'w')\n    open(out)\n")
    assert [(fn, call) for fn, _, call in _direct_writes(f)] == [("g", "write_text"), ("g", "savefig"),
                                                                  ("g", "to_parquet"), ("g", "open")]


# Each idea lives in one place. What may be written out only in its home module, with patterns
# read on the code alone (comments and docstrings blanked), and the MAD factor anywhere at all.
ONE_PLACE = {
    "the robust scale (1.4826 x MAD): mmgp.data.statistics.mad_sd": (
        "mmgp.data.statistics", [r"\b1\.4826", r"\b0\.674[45]", r"median\(\s*(np\.|numpy\.)?abs\(",
                                 r"median\(\s*[^()]*\)\s*\.\s*abs\("]),
    "a Gaussian log density: mmgp.gp.linalg.gaussian_logpdf": (
        "mmgp.gp.linalg", [r"(log|sqrt)\(\s*2(\.0*)?\s*\*\s*(np\.|numpy\.|math\.|torch\.)?pi\b",
                           r"(log|sqrt)\(\s*(np\.|numpy\.|math\.|torch\.)?pi\s*\*\s*2", r"\b1\.83787", r"\b0\.918938",
                           # log 2 pi added to a log variance is the elementwise density; N * LOG_2PI a joint one
                           r"LOG_2PI\s*\+", r"\+\s*LOG_2PI\b"]),
    "a thread limit: mmgp.threads": (
        "mmgp.threads", [r"threadpool_limits", r"set_num_threads", r"_NUM_THREADS\b", r"sched_getaffinity"]),
    "the GP's state inputs: mmgp.labelling.features.StateFeatures": (
        "mmgp.labelling.features", [r"(concatenate|hstack|column_stack)\(\s*\[\s*[\w.]*\bq\s*,\s*[\w.]*\bdq\s*,"]),
}


def _code_text(path: Path) -> str:
    """``path``'s source with its comments and docstrings blanked (other strings kept): what runs."""
    import io
    import tokenize

    src = path.read_text()
    starts = [0]
    for line in src.splitlines(keepends=True):
        starts.append(starts[-1] + len(line))
    docs = {(n.body[0].lineno, n.body[0].col_offset) for n in ast.walk(ast.parse(src))
            if isinstance(n, (ast.Module, ast.ClassDef, ast.FunctionDef, ast.AsyncFunctionDef)) and n.body
            and isinstance(n.body[0], ast.Expr) and isinstance(n.body[0].value, ast.Constant)
            and isinstance(n.body[0].value.value, str)}
    chars = list(src)
    for tok in tokenize.generate_tokens(io.StringIO(src).readline):
        if tok.type == tokenize.COMMENT or (tok.type == tokenize.STRING and tok.start in docs):
            a = starts[tok.start[0] - 1] + tok.start[1]
            b = starts[tok.end[0] - 1] + tok.end[1]
            chars[a:b] = [c if c == "\n" else " " for c in chars[a:b]]
    return "".join(chars)


def _written_out(module: str, path: Path) -> list[str]:
    import re

    code, text = _code_text(path), path.read_text()
    found = []
    for idea, (home, patterns) in ONE_PLACE.items():
        if module == home:
            continue
        for pat in patterns:
            # the MAD factor may not appear even in prose: the helper's docstring states it
            where = text if pat == r"\b1\.4826" else code
            found += [f"{idea} written out ({m.group(0)!r})" for m in re.finditer(pat, where)]
    return found


def test_each_idea_is_written_out_in_one_place_only():
    bad = [f"{p.relative_to(PKG.parent)}: {what}" for m, p in _modules() for what in _written_out(m, p)]
    assert not bad, "written out outside its home module:\n" + "\n".join(bad)


def test_the_one_place_rule_catches_copies(tmp_path):
    # Each idea's usual spellings are caught; comments and docstrings (but for the MAD factor) are not code.
    f = tmp_path / "x.py"
    f.write_text('def f(x, m, v):\n    """log(2 * pi) in prose is fine."""\n    # np.log(2 * np.pi) in a comment too\n'
                 "    s = 1.4826 * np.median(np.abs(x - np.median(x)))\n"
                 "    a = -0.5 * (np.log(2 * np.pi * v) + (x - m) ** 2 / v)\n"
                 "    b = -0.5 * math.log(2.0 * math.pi) - torch.log(torch.sqrt(2 * torch.pi * v))\n"
                 "    c = -0.5 * (LOG_2PI + np.log(v)) - 0.5 * len(x) * LOG_2PI\n"
                 "    with threadpool_limits(1):\n        torch.set_num_threads(1)\n"
                 "    X = np.concatenate([log.q, log.dq, log.ddq], axis=1)\n"
                 "    return {'OMP_NUM_THREADS': '1'}\n")
    found = _written_out("mmgp.labelling.x", f)
    counts = {idea: sum(idea in w for w in found) for idea in ONE_PLACE}
    assert list(counts.values()) == [2, 4, 3, 1], found
    assert _written_out("mmgp.gp.linalg", f) == [w for w in found if "Gaussian" not in w]
    g = tmp_path / "y.py"
    g.write_text('"""1.4826 x the MAD."""\n')
    assert len(_written_out("mmgp.labelling.y", g)) == 1 and _written_out("mmgp.data.statistics", g) == []


def _package(module: str) -> str:
    """The package a module belongs to: ``mmgp.gp.exact`` -> ``mmgp.gp``; top-level modules are
    each their own (``mmgp.estimator``)."""
    parts = module.split(".")
    return ".".join(parts[:2])


def _private_reads(modules) -> list[str]:
    """Private names (one leading underscore) a module takes from another package: imported by
    name (``from ..data.folds import _blocks``), or read as an attribute (``obj._zs``) where only
    other packages define that name (as a function, a class, a class attribute or ``self._x``)."""
    defined, reads = {}, []
    for module, path in modules:
        pkg = _package(module)
        is_pkg = path.name == "__init__.py"
        home = module if is_pkg else module.rsplit(".", 1)[0]
        for node in ast.walk(ast.parse(path.read_text())):
            private = lambda name: name.startswith("_") and not name.startswith("__")  # noqa: E731
            if isinstance(node, (ast.FunctionDef, ast.ClassDef)) and private(node.name):
                defined.setdefault(node.name, set()).add(pkg)
            elif isinstance(node, ast.AnnAssign) and isinstance(node.target, ast.Name) and private(node.target.id):
                defined.setdefault(node.target.id, set()).add(pkg)
            elif isinstance(node, ast.Attribute) and private(node.attr):
                if isinstance(node.value, ast.Name) and node.value.id in ("self", "cls"):
                    if isinstance(node.ctx, ast.Store):
                        defined.setdefault(node.attr, set()).add(pkg)
                else:
                    reads.append((pkg, f"{path.name}:{node.lineno} {ast.unparse(node)}", node.attr))
            elif isinstance(node, ast.ImportFrom) and node.level:
                base = home.split(".")
                target = ".".join(base[:len(base) - (node.level - 1)] + ([node.module] if node.module else []))
                for a in node.names:
                    if private(a.name) and _package(target) != pkg:
                        reads.append((pkg, f"{path.name}:{node.lineno} from {target} import {a.name}", None))
    return [where for pkg, where, attr in reads
            if attr is None or (attr in defined and pkg not in defined[attr])]


def test_no_private_name_is_read_across_packages():
    bad = _private_reads(_modules())
    assert not bad, "private names read from another package:\n" + "\n".join(bad)


def test_the_private_rule_catches_reads_across_packages(tmp_path):
    (tmp_path / "a.py").write_text("from ..data.folds import _blocks\nfrom .common import _fail\n")
    (tmp_path / "b.py").write_text("class G:\n    def fit(self):\n        self._zs = 1\n")
    (tmp_path / "c.py").write_text("def f(g, h):\n    return g._zs + h._other\n")
    modules = [("mmgp.gp.a", tmp_path / "a.py"), ("mmgp.compensator.b", tmp_path / "b.py"),
               ("mmgp.diagnosis.c", tmp_path / "c.py")]
    bad = _private_reads(modules)
    assert bad == ["a.py:1 from mmgp.data.folds import _blocks", "c.py:2 g._zs"]
