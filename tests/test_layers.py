"""The house is one-way: world -> tools -> models -> training -> eval -> robot side -> simulator
side -> CLI. No module imports a layer above its own (imports inside functions count too), no
module loads another by name at run time (__import__ / importlib), and the robot side (what a
robot's computer installs) reaches neither JAX, MuJoCo, flax, optax, orbax, brax nor the trainer,
through any chain of imports."""
import ast
import os

import pytest

from ttmjx.entry import SIMULATOR_PACKAGES

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
# The layers, lowest first. A module may import its own layer and the layers below it.
LAYERS = ["ttmjx.world", "ttmjx.commandline", "ttmjx.tools", "models", "training", "eval", "deploy.robot",
          "deploy.sim", "ttmjx.cli", "ttmjx.entry", "ttmjx.__main__"]
PACKAGES = ("ttmjx", "models", "training", "eval", "deploy")


def layer_of(module: str) -> int | None:
    """Rank of a dotted module name (None: not part of the project, e.g. numpy)."""
    best = None
    for rank, prefix in enumerate(LAYERS):
        if module == prefix or module.startswith(prefix + "."):
            best = rank
    if best is None and module.split(".")[0] in PACKAGES and module not in ("ttmjx", "deploy"):
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
        if name not in ("ttmjx", "deploy"):
            assert layer_of(name) is not None, name


@pytest.mark.parametrize("name,path", MODULES, ids=[m for m, _ in MODULES])
def test_no_module_imports_a_layer_above_it(name, path):
    if name in ("ttmjx", "deploy"):
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


# -- the robot side ---------------------------------------------------------------------------
# What a robot's computer does not install, and the project's layers it must not reach.
ROBOT_FORBIDDEN = SIMULATOR_PACKAGES + ("torch", "ttmjx.tools", "ttmjx.cli", "models", "training", "eval",
                                        "deploy.sim")
PATHS = dict(MODULES)


def module_of(target: str) -> str | None:
    """The project module an imported name lives in (`ttmjx.world.config.World` ->
    ttmjx.world.config), or None outside the project."""
    parts = target.split(".")
    for n in range(len(parts), 0, -1):
        if ".".join(parts[:n]) in PATHS:
            return ".".join(parts[:n])
    return None


def forbidden_chain(name: str) -> list[str] | None:
    """The chain of imports (module, ..., forbidden target) by which `name` reaches a forbidden
    module, following every import of every project module it reaches (nested ones included);
    None if there is none."""
    seen, stack = {name}, [[name]]
    while stack:
        chain = stack.pop()
        for _, target in imports_of(PATHS[chain[-1]]):
            if any(target == f or target.startswith(f + ".") for f in ROBOT_FORBIDDEN):
                return chain + [target]
            inner = module_of(target)
            if inner is not None and inner not in seen:
                seen.add(inner)
                stack.append(chain + [inner])
    return None


ROBOT = [m for m, _ in MODULES if m == "deploy.robot" or m.startswith("deploy.robot.")]


def test_the_robot_side_is_there():
    assert {"deploy.robot.runner", "deploy.robot.exported", "deploy.robot.cli", "deploy.robot.drivers.cell"} <= set(ROBOT)


@pytest.mark.parametrize("name", ROBOT)
def test_the_robot_side_reaches_no_jax_mujoco_or_trainer(name):
    chain = forbidden_chain(name)
    assert chain is None, " -> ".join(chain)


def test_the_robot_check_follows_chains(tmp_path, monkeypatch):
    """The rule can fail: a robot module that imports a world module that imports JAX inside a
    function is caught, with the chain."""
    (tmp_path / "a.py").write_text("from ttmjx.world import b\n")
    (tmp_path / "b.py").write_text("def f():\n    import jax.numpy as jnp\n")
    monkeypatch.setitem(PATHS, "deploy.robot.a", str(tmp_path / "a.py"))
    monkeypatch.setitem(PATHS, "ttmjx.world.b", str(tmp_path / "b.py"))
    assert forbidden_chain("deploy.robot.a") == ["deploy.robot.a", "ttmjx.world.b", "jax.numpy"]
