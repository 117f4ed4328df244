"""Every name the docs write in backquotes exists (issue 23 item 5): docs cannot go stale silently.

docs/*.md and README.md name code in inline backquotes. Each span is classified by its
shape, and each class is checked against the code, in-process:

* ``rig CMD ... --option``: the command path and every option are in the typer app's click
  command (``typer.main.get_command``); a bare ``--option`` is an option of some command;
* a path (``rig/kinematics/steps.py``, ``docs/trial.md``, ``../shared/specs/...``): the file or
  folder exists (globs match something); ``file.py:name`` / ``file.py::test`` also name a
  definition in that file; a bare ``writer.py`` is a file somewhere in the tree;
* a dotted name under ``rig``, ``drivers`` or ``trajectories`` (``rig.kinematics.detect_steps``):
  it imports and resolves;
* ``Class.attr``, ``module.name``: the class or module is defined and names the attribute;
* ``CamelCase``, ``UPPER_CASE`` and ``name(...)``: a definition (def, class, assignment,
  argument or field) in the code;
* a bare ``snake_case`` word (a JSON key, a metadata key, a config field): it occurs in the
  code, the configuration or the specs.

Everything else (values, formulas, YAML snippets, shell lines) is not a name: the shapes above
are the allowlist, and the few name-shaped spans that are not code are listed by pattern in
``NOT_NAMES``.
"""

from __future__ import annotations

import ast
import functools
import glob
import importlib
import re
from pathlib import Path

import fnmatch

import pytest
import typer

SELF = Path(__file__).resolve()
ROOT = next(p for p in SELF.parents if (p / "pyproject.toml").is_file())  # wherever tests/ puts this file
DOCS = sorted((ROOT / "docs").glob("*.md")) + [ROOT / "README.md"]
CODE_DIRS = ("rig", "drivers", "trajectories", "benchmarks")
TEXT_DIRS = ("rig", "drivers", "trajectories", "benchmarks", "tests", "config", ".ci")
SPECS = ROOT.parent / "shared" / "specs"

IDENT = r"[A-Za-z_]\w*"
#: name-shaped spans that are not names of this code base, by pattern
NOT_NAMES = [
    r"rig\.[\w.]+/\d+",                 # JSON schema ids: rig.diagnosis/1
    r"rig\.columns\.v\d(/v\d)?",               # the older raw-channel encodings' names
    r"foxglove\.[\w.]+",                # Foxglove schema names
    r"distributed\.[\w.-]+(: .*)?",     # Dask configuration keys
    r"(np|numpy|math|time|os|sys|json|scipy|typer|click|numba|emcee|mcap|duckdb|dask|pytest|socket|"
    r"signal|subprocess|asyncio|serial|can|pymodbus|pyarrow|pa|pd|plt|matplotlib)\.[\w.()\[\]]+",
    r"self\.\w+.*",
    r"\w+://.*|\$\w+.*",              # URLs, environment variables
    r"Figures/.*",                      # files inside a paper's supplementary archive (validation.md)
]
NOT_NAME_RE = re.compile("|".join(f"(?:{p})" for p in NOT_NAMES))
PATH_SUFFIXES = (".py", ".md", ".yaml", ".yml", ".toml", ".json", ".csv", ".txt", ".png", ".proto", ".cfg",
                 ".mcap", ".parquet", ".duckdb", ".xlsx", ".sock", ".npz")
OUTPUT_PREFIXES = ("out/", "cal/", "/tmp/", "~/", "./", "../../")


def _spans() -> list[tuple[str, str]]:
    """(doc file, span) for every inline code span outside fenced blocks."""
    out = []
    for doc in DOCS:
        text = re.sub(r"```.*?```", "", doc.read_text(), flags=re.S)
        for m in re.finditer(r"(?<!`)`([^`\n]+)`(?!`)", text):
            out.append((doc.name, m.group(1).strip()))
    return out


@functools.cache
def _cli():
    from rig.cli import app

    return typer.main.get_command(app)


@functools.cache
def _all_options() -> frozenset[str]:
    found: set[str] = set()

    def walk(cmd):
        for p in cmd.params:
            found.update(o for o in p.opts + p.secondary_opts if o.startswith("-"))
        for sub in getattr(cmd, "commands", {}).values():
            walk(sub)

    walk(_cli())
    return frozenset(found | {"--help"})


@functools.cache
def _definitions() -> dict[str, set[str]]:
    """name -> the attributes defined under it (for classes: methods, fields, class attributes;
    for a module stem: its top-level names); every defined name is a key."""
    defs: dict[str, set[str]] = {}
    for d in CODE_DIRS:
        for f in (ROOT / d).rglob("*.py"):
            if ".venv" in f.parts or f == SELF:
                continue
            try:
                tree = ast.parse(f.read_text())
            except SyntaxError:
                continue
            top = defs.setdefault(f.stem, set())
            for node in ast.walk(tree):
                names = _defined_names(node)
                for n in names:
                    defs.setdefault(n, set())
                if isinstance(node, ast.ClassDef):
                    defs[node.name].update(n for child in node.body for n in _defined_names(child))
            top.update(n for child in tree.body for n in _defined_names(child))
    return defs


def _defined_names(node) -> list[str]:
    if isinstance(node, (ast.FunctionDef, ast.AsyncFunctionDef, ast.ClassDef)):
        return [node.name] + [a.arg for a in node.args.args + node.args.kwonlyargs] \
            if not isinstance(node, ast.ClassDef) else [node.name]
    if isinstance(node, ast.Assign):
        return [t.id if isinstance(t, ast.Name) else t.attr for t in node.targets
                if isinstance(t, (ast.Name, ast.Attribute))]
    if isinstance(node, ast.AnnAssign) and isinstance(node.target, (ast.Name, ast.Attribute)):
        return [node.target.id if isinstance(node.target, ast.Name) else node.target.attr]
    if isinstance(node, (ast.Import, ast.ImportFrom)):
        return [(a.asname or a.name).split(".")[0] for a in node.names]
    return []


@functools.cache
def _words() -> frozenset[str]:
    """Every identifier-like word in the code, configuration and specs."""
    words: set[str] = set()
    files = [f for d in TEXT_DIRS for f in (ROOT / d).rglob("*") if f.is_file() and ".venv" not in f.parts
             and f != SELF and f.suffix in (".py", ".yaml", ".yml", ".json", ".toml", ".proto", "")]
    files += [ROOT / "pyproject.toml"] + (sorted(SPECS.glob("*.md")) if SPECS.is_dir() else [])
    files += sorted((ROOT.parent / "shared" / "data" / "real").glob("*.md"))
    heads = [f for d in (ROOT / "tests" / "data", ROOT.parent / "shared" / "data" / "real") for f in d.glob("*.csv")]
    for f in files + heads:  # a data file's metadata lines (its own column names), not its rows
        try:
            with f.open(errors="ignore") as fh:
                text = fh.read() if f not in heads else "".join(next(fh, "") for _ in range(40))
        except OSError:
            continue
        words.update(re.findall(r"[A-Za-z_][\w-]*", text))
    return frozenset(words)


@functools.cache
def _code_text() -> str:
    """The Python sources as one text, for literals (schema names, benchmark options)."""
    return "\n".join(f.read_text(errors="ignore") for d in CODE_DIRS for f in (ROOT / d).rglob("*.py")
                     if ".venv" not in f.parts and f != SELF)


def _check_cli(span: str) -> str | None:
    tokens = span.replace("\\|", " ").replace("|", " ").replace("[", " ").replace("]", " ").split()
    cmd = _cli()  # typer's click Group (typer may carry its own click: duck-typed)
    path = ["rig"]
    for tok in tokens[1:]:
        if hasattr(cmd, "commands") and tok in cmd.commands:
            cmd = cmd.commands[tok]
            path.append(tok)
        elif hasattr(cmd, "commands") and re.fullmatch(r"[a-z][a-z-]+", tok) and len(path) == 1:
            return f"no command {' '.join(path + [tok])!r}"
        else:
            break
    opts = {o for p in cmd.params for o in p.opts + p.secondary_opts} | {"--help"}
    for tok in tokens[1:]:
        opt = tok.split("=", 1)[0]
        if re.fullmatch(r"--?[a-z][\w-]*", opt) and opt not in opts:
            return f"{' '.join(path)} has no option {opt!r}"
    return None


def _check_path(span: str) -> str | None:
    span = span.rstrip("/").split(" ", 1)[0]
    name = None
    if "::" in span:
        span, name = span.split("::", 1)
        name = name.split("[")[0].split("::")[-1]
    elif re.search(r"\.py:\w", span):
        span, name = span.split(":", 1)
        name = m.group(0) if (m := re.match(IDENT, name)) else None  # file.py:123 is a line
    if any(c in span for c in "*?"):
        return None if glob.glob(str(ROOT / span)) else f"no file matches {span!r}"
    if "/" not in span:
        hits = [f for d in (*TEXT_DIRS, "docs") for f in (ROOT / d).rglob(span)] + list(ROOT.glob(span))
        if not hits:
            return f"no file named {span!r}"
        f = hits[0]
    else:
        f = ROOT / span
        if not f.exists() and span.startswith("rig/") is False:
            # a docs-relative link; a rig/ subpath; a test file named by its file, wherever under
            # tests/ the suite's layout (tests/unit/<package>/, tests/system/) has put it
            moved = list((ROOT / "tests").rglob(Path(span).name)) if span.startswith("tests/test_") else []
            for alt in (ROOT / "docs" / span, ROOT / "rig" / span, *moved):
                if alt.exists():
                    f = alt
        if not f.exists():
            return f"no file {span!r}"
    if name and f.suffix == ".py" and not fnmatch.filter({n for node in ast.walk(ast.parse(f.read_text()))
                                                          for n in _defined_names(node)}, name):
        return f"{span} defines no {name!r}"
    return None


def _check_dotted(span: str) -> str | None:
    dotted = re.sub(r"\(.*\)$", "", span)
    parts = dotted.split(".")
    if re.fullmatch(r"rig\.[A-Z]\w*", dotted):  # a message schema of the log (rig.LoopBlock, rig.Event)
        return None if f'"{dotted}"' in _code_text() else f"no schema named {dotted!r} in the code"
    if parts[0] in ("rig", "drivers", "trajectories"):
        for i in range(len(parts), 0, -1):
            try:
                obj = importlib.import_module(".".join(parts[:i]))
            except ImportError:
                continue
            for attr in parts[i:]:
                if not hasattr(obj, attr):
                    if attr in _definitions().get(type(obj).__name__, ()):
                        return None
                    return f"{'.'.join(parts[:i])} has no {'.'.join(parts[i:])!r}"
                obj = getattr(obj, attr)
            return None
        return f"cannot import {dotted!r}"
    owner, attr = parts[-2], parts[-1]
    defs = _definitions()
    if owner in defs and (attr in defs[owner] or attr in _words()):
        return None
    if owner not in defs and owner in _words() and attr in _words():
        return None  # a configuration key path (sim.initial_creep_um_s)
    return f"{owner!r} defines no {attr!r}"


def _is_path(span: str) -> bool:
    s = span.split(" ", 1)[0]
    first = s.split("/", 1)[0]
    return ("/" in s and " " not in span.strip() and re.fullmatch(r"\.\.?|[\w-]+", first) is not None) \
        or s.endswith(PATH_SUFFIXES) or ".py:" in s


def check(span: str) -> str | None:
    """None when the span is fine or not a name; else what is wrong."""
    if NOT_NAME_RE.fullmatch(span):
        return None
    if re.fullmatch(r"rig [a-z][a-z-]*( .*)?", span):
        return _check_cli(span)
    if re.fullmatch(r"--[a-z][\w-]*( .*)?", span):
        opt = span.split()[0].split("=")[0]
        if opt in _all_options() or f'"{opt}"' in _code_text():  # rig's, or a benchmark script's
            return None
        return f"no command (nor benchmark) has the option {opt!r}"
    if _is_path(span):
        s = span.split(" ", 1)[0]
        if s.startswith(OUTPUT_PREFIXES) or re.search(r"(^|/)[A-Z][A-Z_-]*(/|\.\w+$|$)", s) or \
                re.search(r"[<{]|\.\.\.", s) or s.startswith("../shared") and not SPECS.is_dir():
            return None  # an output or a placeholder (F.mcap, PROFILE)
        if s.startswith("../"):
            found = glob.glob(str(ROOT / s)) if any(c in s for c in "*?") else (ROOT / s).exists()
            return None if found else f"no file {s!r}"
        if "/" not in s and not s.endswith((".py", ".md")):
            return None  # a bare data file name is an example (recipe.yaml, gains.yaml)
        return _check_path(span)
    if re.fullmatch(rf"{IDENT}(\.{IDENT})+(\(.*\))?", span):
        return _check_dotted(span)
    if re.fullmatch(rf"{IDENT}\(.*\)", span) or re.fullmatch(r"_?[A-Z][a-z]\w*|[A-Z][A-Z0-9]*_[A-Z0-9_]*", span):
        name = span.split("(")[0]  # defined here, or a library's name the code uses (np.geomspace)
        return None if name in _definitions() or name in _words() else f"no definition of {name!r}"
    if re.fullmatch(r"_?[a-z][a-z0-9]*(_[a-z0-9A-Z]+)+", span):
        head, _, tail = span.partition("_")  # or a composed key: f"{device}_dither_gain_min"
        if span in _words() or (head in _words() and f"_{tail}" in _code_text()):
            return None
        return f"{span!r} occurs nowhere in the code, config or specs"
    return None


def test_docs_name_only_what_exists():
    wrong = sorted({f"{doc}: `{span}`: {why}" for doc, span in _spans() if (why := check(span))})
    assert not wrong, "stale names in the docs:\n" + "\n".join(wrong)


@pytest.mark.parametrize("span, ok", [
    ("rig run RECIPE --sim --out F.mcap", True),
    ("rig run RECIPE --no-such-option", False),
    ("rig no-such-command", False),
    ("--overwrite", True),
    ("--frobnicate", False),
    ("rig/kinematics/steps.py", True),
    ("rig/kinematics.py", False),
    ("rig/data.py:read_csv", True),
    ("rig/data.py:no_such_function", False),
    ("rig.kinematics.detect_steps", True),
    ("rig.kinematics.no_such_name", False),
    ("TrialData.is_load_point", True),
    ("TrialData.no_such_property", False),
    ("DataFormatError", True),
    ("NoSuchClass", False),
    ("read_csv(path)", True),
    ("position_source", True),
    ("no_such_key_anywhere_xyz", False),
    ("2 N (B_mu - A_mu) / L", True),
    ("rig.diagnosis/1", True),
])
def test_the_checker_tells_names_that_exist_from_names_that_do_not(span, ok):
    assert (check(span) is None) is ok, check(span)
