"""The package's layers point one way: no module of ``delta`` imports from a higher layer.

``LAYERS`` lists the layers, lowest first. Each layer holds one or more units (a subpackage, or a
top-level module); a module may import from its own unit and from any unit of a lower layer. Units
that share a layer are peers that do not import each other: putting them side by side says they are
independent. Every import counts: at module level, inside functions, under ``TYPE_CHECKING``,
``from delta.x import y``, ``import delta.x``, relative imports and ``importlib.import_module("delta.x")``.

A new subpackage or top-level module goes into the lowest layer its imports allow; a module that
needs something from a higher layer is a sign that the thing belongs lower (move it, do not re-export it).
"""

from __future__ import annotations

import ast
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]

#: Lowest first. Why this order:
#:
#: * the building blocks know nothing of avatars: the body model, cameras, geometry queries, neural
#:   fields, image metrics and perceptual networks; above them the frame data (records, their sources,
#:   frames at a resolution and ray sampling), the losses and the backward deformer, then the renderer
#:   that composes a deformer with the geometry;
#: * ``delta.models`` is the avatar built from those pieces, with its whole-image render
#:   (``delta.models.image``: it renders an avatar, so it cannot sit in ``delta.render``);
#: * the stages follow the workflow: a capture's frame record is made (``preprocess``, or the
#:   ``synthetic`` generator), the body is fitted, the avatar trained, exported, then evaluated
#:   (evaluation scores the exported clothing mesh, and loads the trained model as training left it);
#:   the applications use the trained avatar (and its exports);
#: * on top, the entry points: the workflow configuration's validation (it resolves presets and fit
#:   settings), then the configuration reference generated from its schema, and the command line.
LAYERS: tuple[tuple[str, ...], ...] = (
    ("delta",),  # the package root: DeltaError, __version__
    (
        "delta.io",
        "delta.safe_pickle",
        "delta.settings",
        "delta.progress",
        "delta.loss_weights",
        "delta.optim",
        "delta.devices",
        "delta.host_memory",
    ),  # files, unpickling, settings, progress, loss weights, the optimiser, the host's or a GPU's paths, the
    # host's allocator
    ("delta.body", "delta.cameras", "delta.geometry", "delta.fields", "delta.metrics", "delta.perceptual"),
    ("delta.data", "delta.losses", "delta.deformers"),
    ("delta.render",),
    ("delta.models",),
    ("delta.preprocess", "delta.synthetic"),
    ("delta.fitting",),
    ("delta.scene",),  # what a capture requires modelled, from its frames and init fit
    ("delta.training",),
    ("delta.export",),
    ("delta.eval",),
    ("delta.applications",),  # the trained avatar in use: driven by new motion
    ("delta.config",),
    ("delta.config_reference", "delta.cli"),
)


def module_name(path: Path, root: Path) -> str:
    """``delta.x.y`` for ``root/delta/x/y.py``; a package's ``__init__.py`` is the package itself."""
    parts = list(path.relative_to(root).with_suffix("").parts)
    if parts[-1] == "__init__":
        parts.pop()
    return ".".join(parts)


def unit_of(module: str, layers=LAYERS) -> str | None:
    """The unit of ``LAYERS`` that holds ``module`` (the root unit ``delta`` holds only the root itself)."""
    best = None
    for layer in layers:
        for unit in layer:
            if module == unit or (unit != "delta" and module.startswith(unit + ".")):
                if best is None or len(unit) > len(best):
                    best = unit
    return best


def imported_modules(tree: ast.AST, module: str, is_package: bool, known: set[str]) -> list[tuple[int, str]]:
    """(line, module) of every ``delta`` module that ``tree`` (the source of ``module``) imports."""
    out = []
    package = module if is_package else module.rpartition(".")[0]
    for node in ast.walk(tree):
        if isinstance(node, ast.Import):
            out += [(node.lineno, a.name) for a in node.names]
        elif isinstance(node, ast.ImportFrom):
            if node.level:
                base = package.split(".")
                base = base[: len(base) - (node.level - 1)] if node.level > 1 else base
                source = ".".join(base + ([node.module] if node.module else []))
            else:
                source = node.module or ""
            for a in node.names:  # ``from delta import losses`` imports the module delta.losses
                sub = f"{source}.{a.name}"
                out.append((node.lineno, sub if sub in known else source))
        elif isinstance(node, ast.Call) and node.args and isinstance(node.args[0], ast.Constant):
            name = node.func.attr if isinstance(node.func, ast.Attribute) else getattr(node.func, "id", "")
            if name in ("import_module", "__import__") and isinstance(node.args[0].value, str):
                out.append((node.lineno, node.args[0].value))
    return [(line, m) for line, m in out if m == "delta" or m.startswith("delta.")]


def layer_violations(root: Path, layers=LAYERS) -> list[str]:
    """Every import of ``root/delta/**/*.py`` that points up (or sideways to a peer unit), as
    ``file:line imports module (layer A -> layer B)``; modules in no layer are reported too."""
    index = {unit: i for i, layer in enumerate(layers) for unit in layer}
    label = lambda unit: f"layer {index[unit]} {unit}"  # noqa: E731
    files = sorted((root / "delta").rglob("*.py"))
    known = {module_name(p, root) for p in files}
    problems = []
    for path in files:
        module = module_name(path, root)
        rel = path.relative_to(root).as_posix()
        unit = unit_of(module, layers)
        if unit is None:
            problems.append(f"{rel}: {module} is in no layer (add it to LAYERS in tests/test_layers.py)")
            continue
        tree = ast.parse(path.read_text(), filename=rel)
        for line, target in imported_modules(tree, module, path.name == "__init__.py", known):
            other = unit_of(target, layers)
            if other is None:
                problems.append(f"{rel}:{line} imports {target}, which is in no layer")
            elif other != unit and index[other] >= index[unit]:
                how = "a peer in the same layer" if index[other] == index[unit] else "a higher layer"
                problems.append(f"{rel}:{line} imports {target} ({label(unit)} -> {label(other)}: {how})")
    return problems


def test_no_module_imports_from_a_higher_layer():
    problems = layer_violations(REPO)
    assert not problems, "imports that point up the layers (lowest first: LAYERS):\n" + "\n".join(problems)


def test_every_layer_unit_exists():
    for layer in LAYERS:
        for unit in layer:
            path = REPO / Path(*unit.split("."))
            assert path.with_suffix(".py").is_file() or (path / "__init__.py").is_file(), f"{unit}: no such module"
    units = [u for layer in LAYERS for u in layer]
    assert len(units) == len(set(units)), "a unit is in two layers"


def _tree(root: Path, files: dict[str, str]) -> Path:
    for name, text in files.items():
        path = root / name
        path.parent.mkdir(parents=True, exist_ok=True)
        path.write_text(text)
    return root


def test_the_checker_catches_imports_that_point_up(tmp_path):
    layers = (("delta",), ("delta.low", "delta.side"), ("delta.high",))
    root = _tree(
        tmp_path,
        {
            "delta/__init__.py": "class DeltaError(Exception):\n    pass\n",
            "delta/low/__init__.py": "",
            "delta/low/a.py": (
                "from delta import DeltaError\n"  # down: fine
                "from delta.low import b\n"  # its own unit: fine
                "\n\ndef f():\n"
                "    from delta.high.c import g\n"  # line 6, function-local: up
                "    return g\n"
            ),
            "delta/low/b.py": (
                "import delta.high.c as c\n"  # line 1: up
                "from ..high import c\n"  # line 2: relative, up
                "from delta import side\n"  # line 3: a peer
                "import importlib\n"
                "m = importlib.import_module('delta.high')\n"  # line 5: up
            ),
            "delta/side.py": "",
            "delta/high/__init__.py": "from . import c\n",  # its own unit
            "delta/high/c.py": "from delta.low.a import f\nfrom delta.low import b\n\n\ndef g():\n    return f\n",  # down
            "delta/stray.py": "",
        },
    )
    problems = layer_violations(root, layers)
    assert sorted(problems) == sorted(
        [
            "delta/low/a.py:6 imports delta.high.c (layer 1 delta.low -> layer 2 delta.high: a higher layer)",
            "delta/low/b.py:1 imports delta.high.c (layer 1 delta.low -> layer 2 delta.high: a higher layer)",
            "delta/low/b.py:2 imports delta.high.c (layer 1 delta.low -> layer 2 delta.high: a higher layer)",
            "delta/low/b.py:3 imports delta.side (layer 1 delta.low -> layer 1 delta.side: a peer in the same layer)",
            "delta/low/b.py:5 imports delta.high (layer 1 delta.low -> layer 2 delta.high: a higher layer)",
            "delta/stray.py: delta.stray is in no layer (add it to LAYERS in tests/test_layers.py)",
        ]
    ), "\n".join(problems)


def test_the_checker_reads_the_packages_own_imports():
    """The map is read from the real tree: e.g. the avatar imports the renderer, the CLI everything."""
    files = sorted((REPO / "delta").rglob("*.py"))
    known = {module_name(p, REPO) for p in files}
    path = REPO / "delta" / "models" / "avatar.py"
    found = {m for _, m in imported_modules(ast.parse(path.read_text()), "delta.models.avatar", False, known)}
    assert {"delta.render.hybrid", "delta.body.parts", "delta.deformers.knn"} <= found
    assert unit_of("delta.models.image") == "delta.models" and unit_of("delta") == "delta"
    assert unit_of("delta.metrics") == "delta.metrics" and unit_of("deltax") is None
