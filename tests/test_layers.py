"""The import direction of every folder of the package: a module imports only from its own folder
and from folders of a lower layer. Imports inside functions (lazy ones) count as much as those at
the top of a module.

The layers, lowest first (a folder may import every folder of a lower layer):

====  =========================================  ==================================================
rank  folders (and root modules)                 what they are
====  =========================================  ==================================================
0     errors                                     the exception family and exit codes
1     units, formats, jsoncheck                  length units; shared facts of the file formats;
                                                 the check of a JSON document against a schema
2     inference, io                              the inference motor (arrays in, arrays out); the
                                                 point-cloud file formats (no engine, no rules)
3     geometry                                   pure geometry of point sets (PCA, connexity, the
                                                 ground surfaces); uses inference's compiled kernels
4     knowledge                                  rule bases, predicates, interpreter, explanations
5     evaluation, report, tiles                  scores, reports and figures, tiled runs
6     maps                                       maps fused from runs (its reports, its tiles)
7     synth                                      generated scenes (a synthetic drive writes the
                                                 maps' poses file)
8     cli, the package root ``kbs/__init__.py``  the commands; the facade (``kbs.segment``,
                                                 ``kbs.segment_tiled``, imported when first used)
====  =========================================  ==================================================

Any module may read ``kbs.__version__`` from the package root (package metadata).

Third-party boundaries: ``yaml`` only in knowledge (rule files) and cli; ``click`` only in cli.

Exceptions (each with its reason) are in :data:`EXCEPTIONS`.

Private names: a module imports no private module or name (leading underscore) from another
folder; inside a folder its modules share what they like. The exceptions that remain are in
:data:`PRIVATE_EXCEPTIONS`, each with its reason.
"""
from __future__ import annotations

import ast
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]

LAYERS: dict[str, int] = {
    "errors": 0,
    "units": 1, "formats": 1, "jsoncheck": 1, "arrays": 1,
    "inference": 2, "io": 2,
    "geometry": 3,
    "knowledge": 4,
    "evaluation": 5, "report": 5, "tiles": 5,
    "maps": 6,
    "synth": 7,
    "cli": 8, "kbs": 8,
}
#: Folders that are not library code walked here: data (rules), scripts and tests.
NOT_LIBRARY = {"rules", "examples", "tests", "benchmarks", "docs", ".venv", "kbs.egg-info", "build"}

#: (importing module, imported module) -> why it is allowed.
EXCEPTIONS: dict[tuple[str, str], str] = {}

#: (importing folder, imported module) -> why it may use that module's private names.
PRIVATE_EXCEPTIONS: dict[tuple[str, str], str] = {
    ("geometry", "kbs.inference"): "the compiled kernels (_compiled, numba) and their switch (_flags): one "
                                   "compiled module, one warm-up, one KBS_JIT for the whole library",
    ("tiles", "kbs.inference"): "as above (_flags: the streamed sums take the compiled path as the engine does; "
                                "_compiled.covariance_eigen: their eigenvectors are geometry3's, by the same solver)",
    ("cli", "kbs.inference"): "kbs warmup runs the compiled kernels' warm-up (_flags, _warmup)",
    ("knowledge", "kbs.inference"): "the rule files known to pass the schema are kept in the compiled kernels' "
                                    "state folder (_flags._state_dir: one KBS_CACHE_DIR)",
}

THIRD_PARTY = {"yaml": {"knowledge", "cli"}, "click": {"cli"}}


def _folder(module: str) -> str:
    """'kbs.knowledge.rulebase' -> 'knowledge'; 'kbs.errors' -> 'errors'; 'kbs' -> 'kbs'."""
    parts = module.split(".")
    return parts[1] if len(parts) > 1 else "kbs"


def _library_modules(root: Path) -> dict[str, Path]:
    out = {}
    for path in sorted(root.rglob("*.py")):
        rel = path.relative_to(root)
        if rel.parts[0] in NOT_LIBRARY or len(rel.parts) > 2 and rel.parts[0] not in LAYERS:
            continue
        name = ".".join(("kbs", *rel.with_suffix("").parts))
        out[name.removesuffix(".__init__")] = path
    return out


def _imports(module: str, path: Path) -> list[tuple[str, int, list[str]]]:
    """(imported module, line, names) of every import in the file, relative ones resolved."""
    tree = ast.parse(path.read_text(), filename=str(path))
    package = module if path.name == "__init__.py" else module.rpartition(".")[0]
    found = []
    for node in ast.walk(tree):
        if isinstance(node, ast.Import):
            found += [(a.name, node.lineno, []) for a in node.names]
        elif isinstance(node, ast.ImportFrom):
            names = [a.name for a in node.names]
            if node.level:
                base = package.split(".")[: len(package.split(".")) - (node.level - 1)]
                target = ".".join(base + ([node.module] if node.module else []))
            else:
                target = node.module or ""
            found.append((target, node.lineno, names))
    return found


def _violations(root: Path = ROOT) -> list[str]:
    problems = []
    for module, path in _library_modules(root).items():
        own = _folder(module)
        if own not in LAYERS:
            problems.append(f"{path.relative_to(root)}: folder {own!r} is in no layer (add it to LAYERS)")
            continue
        for target, line, names in _imports(module, path):
            where = f"{path.relative_to(root)}:{line}"
            top = target.split(".")[0]
            if top in THIRD_PARTY and own not in THIRD_PARTY[top]:
                problems.append(f"{where}: {module} imports {target} (only {sorted(THIRD_PARTY[top])} may)")
            if top != "kbs" or target == module:
                continue
            folder = _folder(target)
            if folder == own or (module, target) in EXCEPTIONS or (module, f"kbs.{folder}") in EXCEPTIONS:
                continue
            private = [n for n in [*target.split(".")[1:], *names] if n.startswith("_") and not n.startswith("__")]
            if private and folder != own and (own, target) not in PRIVATE_EXCEPTIONS:
                problems.append(f"{where}: {module} imports the private {private} of {target} (another folder)")
            if folder == "kbs" and target == "kbs" and set(names) <= {"__version__"}:
                continue  # the package's metadata
            if LAYERS[folder] >= LAYERS[own]:
                problems.append(f"{where}: {module} (layer {LAYERS[own]}, {own}) imports {target} "
                                f"(layer {LAYERS[folder]}, {folder})")
    return problems


def test_every_import_points_down_the_layers():
    assert _violations() == []


def test_every_folder_of_the_package_is_in_a_layer():
    folders = {p.name for p in ROOT.iterdir() if (p / "__init__.py").is_file()} - NOT_LIBRARY
    modules = {p.stem for p in ROOT.glob("*.py")} - {"__init__"}
    assert folders | modules | {"kbs"} == set(LAYERS)


def test_each_exception_is_still_needed():
    """An exception no import uses any more is removed from the table."""
    used, private = set(), set()
    for module, path in _library_modules(ROOT).items():
        for target, _, names in _imports(module, path):
            if target.startswith("kbs"):
                used.add((module, target))
                used.add((module, f"kbs.{_folder(target)}"))
                if any(n.startswith("_") and not n.startswith("__") for n in [*target.split(".")[1:], *names]):
                    private.add((_folder(module), target))
    assert set(EXCEPTIONS) <= used, set(EXCEPTIONS) - used
    assert set(PRIVATE_EXCEPTIONS) <= private, set(PRIVATE_EXCEPTIONS) - private


@pytest.mark.parametrize("bad, expected", [
    ("from kbs.knowledge.rulebase import RuleBase", "geometry"),
    ("import yaml", "yaml"),
    ("from kbs.io.segcomp import _read_bytes", "private"),
])
def test_the_check_finds_an_upward_import(tmp_path, bad, expected):
    """The walk sees a lazy import in a function (here in a copy of the library with one bad line)."""
    import shutil

    copy = tmp_path / "kbs"
    shutil.copytree(ROOT, copy, ignore=shutil.ignore_patterns(*NOT_LIBRARY, ".*", "__pycache__", "*.egg-info",
                                                              "*.yaml", "*.json", "*.md", "*.ply"))
    target = copy / "geometry" / "pca.py"
    target.write_text(target.read_text() + f"\n\ndef _bad():\n    {bad}\n")
    problems = _violations(copy)
    assert len(problems) == 1 and "geometry/pca.py" in problems[0] and expected in problems[0], problems
