"""The `ttmjx` console script (also `python -m ttmjx` from a source tree): the robot side's
commands (`ttmjx robot run` on the fake station or the cell, `ttmjx robot bench`) go to
deploy/robot/cli.py without importing JAX or MuJoCo, so a robot's computer with `pip install
'ttmjx[robot]'` runs them; every other command, and `robot run --station sim`, goes to the
simulator side's command line (ttmjx/cli.py)."""
from __future__ import annotations

import os
import sys

ROBOT_SIDE = ("robot run", "robot bench")
# What a robot-side install lacks: a command that needs them says so in one line.
SIMULATOR_PACKAGES = ("jax", "jaxlib", "mujoco", "flax", "optax", "orbax", "brax", "matplotlib", "tensorboardX", "tqdm")


def on_robot_side(argv: list[str]) -> bool:
    """Whether argv is a robot-side command that needs no simulator (not --station sim)."""
    if " ".join(argv[:2]) not in ROBOT_SIDE:
        return False
    for i, arg in enumerate(argv):
        if arg == "--station=sim" or (arg == "--station" and argv[i + 1:i + 2] == ["sim"]):
            return False
    return True


def asks_for_the_command_list(argv: list[str]) -> bool:
    """`ttmjx --help` or `ttmjx robot --help` (-h alike)."""
    return argv[-1:] in (["-h"], ["--help"]) and (len(argv) == 1 or (len(argv) == 2 and argv[0] == "robot"))


def robot_side_help(argv: list[str], missing: str) -> str:
    """The command list of an install without the simulator side, and how to get the rest."""
    from deploy.robot.cli import COMMANDS
    from ttmjx.commandline import usage
    return (usage(COMMANDS, "robot" if len(argv) == 2 else "") + f"\nThis install is the robot side ({missing} is "
            "not installed): the simulator's commands (train, eval, demos, export, robot run --station sim, ...) "
            "need pip install 'ttmjx[sim]'.")


def main(argv: list[str] | None = None) -> None:
    if argv is None:
        return as_process(sys.argv[1:])
    if on_robot_side(argv):
        from deploy.robot.cli import main as robot_main
        return robot_main(argv)
    try:
        from ttmjx import cli
    except ImportError as e:
        if (e.name or "").split(".")[0] not in SIMULATOR_PACKAGES:
            raise
        if asks_for_the_command_list(argv):
            print(robot_side_help(argv, e.name))
            sys.exit(0)
        from ttmjx.commandline import fail
        fail(" ".join(argv[:2]) if argv[:1] == ["robot"] else " ".join(argv[:1]),
             f"{e.name} is not installed: this command needs the simulator side (pip install 'ttmjx[sim]'); "
             f"this install runs `ttmjx robot run --station fake|cell` and `ttmjx robot bench`")
    cli.main(argv)


def as_process(argv: list[str]) -> None:
    """main(argv) as the process's own command. A failure of the machine (exit 1: a full disk, a
    permission) ends the process at once after its one line: library threads whose writes were
    failing with it (tensorstore's, under an Orbax save) would print tracebacks after that line
    while Python shuts down."""
    try:
        main(argv)
    except SystemExit as e:
        if e.code != 1:
            raise
        sys.stdout.flush()
        sys.stderr.flush()
        os._exit(1)

