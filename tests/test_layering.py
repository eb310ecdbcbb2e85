"""Imports flow one way (lowest first), and the reference never imports the code it checks."""

import ast
import pathlib

import pytest

PKG = pathlib.Path(__file__).resolve().parents[1] / "jshadow"

# module (top-level name inside jshadow) -> layer; a module may import only equal or lower layers
LAYER = {
    "_types": 0,
    "_numerics": 0,
    "_parallel": 0,
    "_sorting": 0,
    "_active": 0,
    "sh": 1,
    "geometry": 1,
    "entities": 2,
    "visibility": 3,
    "sampling": 3,
    "scaling": 3,
    "lights": 4,
    "envlights": 5,
    "field": 5,
    "scene": 6,
    "reference": 6,
    "compare": 6,
    "optim": 7,
    "runner": 7,
    "readout": 7,
    "picture": 7,
    "config": 8,
    "cli": 9,
    "__init__": 10,
}
REFERENCE_SIDE = {"reference", "sampling"}
SHADOW_FIELD_CODE = {"scaling", "lights", "envlights", "field", "scene", "readout", "runner", "optim"}


def top_module(path: pathlib.Path) -> str:
    rel = path.relative_to(PKG)
    return rel.parts[0].removesuffix(".py")


def jshadow_imports(path: pathlib.Path):
    tree = ast.parse(path.read_text())
    depth = len(path.relative_to(PKG).parts) - 1  # package depth of the file
    for node in ast.walk(tree):
        if isinstance(node, ast.ImportFrom):
            if node.level == 0 and node.module and node.module.startswith("jshadow"):
                parts = node.module.split(".")[1:]
            elif node.level > 0:
                up = node.level - 1
                if up > depth:
                    continue
                base = list(path.relative_to(PKG).parts[: depth - up])
                parts = base + (node.module.split(".") if node.module else [])
                if not node.module:
                    parts = base + [a.name for a in node.names]
            else:
                continue
            if parts:
                yield parts[0].removesuffix(".py"), node.lineno
        elif isinstance(node, ast.Import):
            for a in node.names:
                if a.name.startswith("jshadow."):
                    yield a.name.split(".")[1], node.lineno


FILES = sorted(PKG.rglob("*.py"))


@pytest.mark.parametrize("path", FILES, ids=lambda p: str(p.relative_to(PKG)))
def test_imports_flow_downward(path):
    me = top_module(path)
    assert me in LAYER, f"{me} has no layer in tests/test_layering.py: add it"
    for other, line in jshadow_imports(path):
        if other == me:
            continue
        assert other in LAYER, f"{path.name}:{line} imports unknown jshadow module {other}"
        assert LAYER[other] <= LAYER[me], f"{path.name}:{line}: {me} (layer {LAYER[me]}) imports {other}"
        if me in REFERENCE_SIDE:
            assert other not in SHADOW_FIELD_CODE, f"{path.name}:{line}: the reference imports {other}"
