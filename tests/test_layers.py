"""The house is one-way: world -> tools -> models -> training -> eval -> deploy -> CLI. No module
imports a layer above its own (imports inside functions count too), and no module loads another
by name at run time (__import__ / importlib)."""
import ast
import os

import pytest

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
# The layers, lowest first. A module may import its own layer and the layers below it.
LAYERS = ["ttmjx.world", "ttmjx.tools", "models", "training", "eval", "deploy", "ttmjx.cli"]
PACKAGES = ("ttmjx", "models", "training", "eval", "deploy")


def layer_of(module: str) -> int | None:
    """Rank of a dotted module name (None: not part of the project, e.g. numpy)."""
    best = None
    for rank, prefix in enumerate(LAYERS):
        if module == prefix or module.startswith(prefix + "."):
            best = rank
    if best is None and module.split(".")[0] in PACKAGES and module != "ttmjx":
        raise AssertionError(f"{module} belongs to no layer: add it to LAYERS")
    return best


def project_modules():
    """(dotted name, path) of every project module."""
    for pkg in PACKAGES:
        for dirpath, _, files in os.walk(os.path.join(ROOT, pkg)):
            for f in sorted(files):
                if f.endswith(".py"):
                    path = os.path.join(dirpath, f)
                    rel = os.path.relpath(path, ROOT)[:-3].replace(os.sep, ".")
                    yield rel.removesuffix(".__init__"), path


def imports_of(path: str):
    """(line, imported module) of every absolute import in a file, nested ones included."""
    for node in ast.walk(ast.parse(open(path).read(), path)):
        if isinstance(node, ast.Import):
            yield from ((node.lineno, a.name) for a in node.names)
        elif isinstance(node, ast.ImportFrom) and node.level == 0 and node.module:
            # `from ttmjx.world import env` imports ttmjx.world.env
            yield from ((node.lineno, f"{node.module}.{a.name}") for a in node.names)


MODULES = list(project_modules())


def test_every_module_has_a_layer():
    for name, _ in MODULES:
        if name != "ttmjx":
            assert layer_of(name) is not None, name


@pytest.mark.parametrize("name,path", MODULES, ids=[m for m, _ in MODULES])
def test_no_module_imports_a_layer_above_it(name, path):
    if name == "ttmjx":
        return
    mine = layer_of(name)
    for line, target in imports_of(path):
        rank = layer_of(target) if target.split(".")[0] in PACKAGES else None
        if rank is not None:
            assert rank <= mine, f"{path}:{line}: {name} ({LAYERS[mine]}) imports {target} ({LAYERS[rank]})"


def test_no_module_is_loaded_by_name():
    for name, path in MODULES:
        for node in ast.walk(ast.parse(open(path).read(), path)):
            if isinstance(node, ast.Call):
                f = node.func
                called = f.id if isinstance(f, ast.Name) else f.attr if isinstance(f, ast.Attribute) else ""
                assert called not in ("__import__", "import_module"), f"{path}:{node.lineno} loads a module by name"


def test_the_checker_sees_an_upward_import(tmp_path):
    """The rule can fail: a world module importing training is caught."""
    bad = tmp_path / "bad.py"
    bad.write_text("def f():\n    from training.trainer import Run\n")
    ranks = [layer_of(t) for _, t in imports_of(str(bad))]
    assert ranks == [LAYERS.index("training")] and ranks[0] > layer_of("ttmjx.world.env")
