"""The house rules that a refactor could quietly break: import boundaries and size limits (outside tests)."""

from __future__ import annotations

import ast
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[1]
PACKAGES = ("pusht", "policies", "acting", "service", "clients", "training", "bench", "scripts")
# what each package may import of ours (docs/design.md, README "Layout")
ALLOWED = {
    "pusht": set(),
    "policies": {"pusht"},
    "acting": {"pusht", "policies"},
    "service": {"pusht", "policies", "acting"},
    "clients": {"pusht"},
}
MAX_FUNCTION_LINES, MAX_MODULE_LINES, MAX_PARAMETERS = 60, 400, 8


def _modules(packages=PACKAGES):
    for package in packages:
        yield from sorted((REPO / package).rglob("*.py"))


def _ours(tree: ast.Module) -> set[str]:
    names = set()
    for node in ast.walk(tree):
        if isinstance(node, ast.Import):
            names.update(alias.name.split(".")[0] for alias in node.names)
        elif isinstance(node, ast.ImportFrom) and node.level == 0 and node.module:
            names.add(node.module.split(".")[0])
    return names & set(PACKAGES)


@pytest.mark.parametrize("package", sorted(ALLOWED))
def test_each_package_imports_only_what_the_layout_allows(package: str) -> None:
    wrong = {}
    for path in _modules([package]):
        extra = _ours(ast.parse(path.read_text())) - ALLOWED[package] - {package}
        if extra:
            wrong[str(path.relative_to(REPO))] = sorted(extra)
    assert not wrong, wrong


def test_functions_modules_and_signatures_stay_small() -> None:
    too_big = []
    for path in _modules():
        text = path.read_text()
        name = path.relative_to(REPO)
        if len(text.splitlines()) > MAX_MODULE_LINES:
            too_big.append(f"{name}: {len(text.splitlines())} lines")
        for node in ast.walk(ast.parse(text)):
            if isinstance(node, (ast.FunctionDef, ast.AsyncFunctionDef)):
                lines = node.end_lineno - node.lineno + 1
                args = node.args
                params = [a for a in args.posonlyargs + args.args + args.kwonlyargs if a.arg not in ("self", "cls")]
                if lines > MAX_FUNCTION_LINES:
                    too_big.append(f"{name}:{node.lineno} {node.name}: {lines} lines")
                if len(params) > MAX_PARAMETERS:
                    too_big.append(f"{name}:{node.lineno} {node.name}: {len(params)} parameters")
    assert not too_big, "\n".join(too_big)
