"""The run configuration's command-line flags, one language for every command that builds runs
(`ttmjx train`, `ttmjx ablate`, `ttmjx baseline`): tyro's flags of RunConfig's fields, nested
ones dotted (`--seed 1`, `--train.members 4`, `--demo-source paper`,
`--world.timing.ideal-timing`), each overriding a base configuration (train's preset, a table's
scale). Standard library, tyro and the configs only: the command line parses through here and
the tables apply what changed (eval/ablate.py cell_overrides).
"""
from __future__ import annotations

import dataclasses
from typing import Any, Callable

from ttmjx.commandline import parse_args
from training.runconfig import PRESET_NAMES, RunConfig, preset

# --world.timing.* flags that ideal timing does not reset (the switch itself, and extrapolation).
IDEAL_TIMING_FLAGS = ("--world.timing.ideal-timing", "--world.timing.no-ideal-timing", "--world.timing.extrapolate-s")


def flag_name(arg: str) -> str:
    """'--a_b=V' -> '--a-b': a command-line token's flag as tyro spells it."""
    return arg.split("=")[0].replace("_", "-")


def given(argv: list[str], *flags: str) -> bool:
    """Whether any of `flags` ('--a-b', also spelled --a_b or --a-b=V) is on the command line."""
    return any(flag_name(arg) in flags for arg in argv)


def flag_value(argv: list[str], flag: str, default: str) -> str:
    """The value of `flag` ('--preset P' or '--preset=P'; the last one wins, as in tyro), read
    before tyro parses because it picks the defaults tyro starts from."""
    value = default
    for i, arg in enumerate(argv):
        if arg.startswith(flag + "="):
            value = arg.split("=", 1)[1]
        elif arg == flag and i + 1 < len(argv):
            value = argv[i + 1]
    return value


def preset_named(argv: list[str]) -> tuple[str, RunConfig]:
    """(name, configuration) of the preset `--preset` names (default: 'default'); ValueError
    naming the value otherwise."""
    name = flag_value(argv, "--preset", "default")
    if name not in PRESET_NAMES:
        raise ValueError(f"--preset {name!r}: expected one of {', '.join(PRESET_NAMES)}")
    return name, preset(name)


def parse_config_args(command: str, cls: type, argv: list[str], default: Any, base_name: str) -> Any:
    """tyro on `cls`, whose `config` field is a RunConfig with unprefixed flags, starting from
    `default` (its config the base `base_name` names, e.g. 'preset tiny'). A new control rate
    derives the physics step again unless given; a --world.timing.* flag that ideal timing would
    reset is refused (ValueError naming it)."""
    if given(argv, "--world.control-hz", "--world.max-physics-dt") and not given(argv, "--world.physics-dt"):
        argv = ["--world.physics-dt", "None", *argv]   # derived again from the new rate
    a = parse_args(command, cls, argv, default=default)
    if a.config.world.timing.ideal_timing:
        ignored = [arg.split("=")[0] for arg in argv
                   if arg.startswith("--world.timing.") and flag_name(arg) not in IDEAL_TIMING_FLAGS]
        if ignored:
            raise ValueError(f"{ignored[0]} would be ignored: this run's timing is ideal (--world.timing.ideal-timing, "
                             f"{base_name}), which resets every delay and rate; add --world.timing.no-ideal-timing "
                             f"to use it")
    return a


def parse_cells(command: str, cls: type, argv: list[str], picks: dict | None,
                base_of: Callable[..., tuple[RunConfig, str]]) -> Any:
    """`ablate`, `baseline`: tyro on `cls`, the run-configuration flags as `train` reads them,
    starting from the cells' base `base_of(**picks)` -> (config, its name); `picks` are the
    arguments that choose it, read from argv by hand (None where argv has none valid: then tyro
    refuses or prints --help on its own), read again from tyro's parse where it differs (a value
    such as `--out demos` taken for the ablation). The retired --set is refused, naming the flags
    to write instead."""
    refusal = set_refusal(argv)
    if refusal:
        raise ValueError(refusal)
    if picks is None:
        return parse_args(command, cls, argv)
    for _ in range(2):
        base, where = base_of(**picks)
        a = parse_config_args(command, cls, argv, cls(**picks, config=base), where)
        read = {k: getattr(a, k) for k in picks}
        if read == picks:
            break
        picks = read
    return a


def seed_run_dir(cfg: RunConfig, base: RunConfig, argv: list[str]) -> RunConfig:
    """`cfg` run in the base's run directory + '-seedN' when its seed is not 0 and --run-dir is
    not given (so that seeds of one preset do not resume each other's run)."""
    if cfg.seed == 0 or given(argv, "--run-dir"):
        return cfg
    return dataclasses.replace(cfg, run_dir=f"{base.run_dir}-seed{cfg.seed}")


def changed_fields(base, cfg, prefix: str = "") -> dict:
    """{dotted field: value} of every leaf field where `cfg` differs from `base` (dataclasses of
    one type): what the flags changed."""
    out = {}
    for f in dataclasses.fields(base):
        old, new = getattr(base, f.name), getattr(cfg, f.name)
        if dataclasses.is_dataclass(old) and type(old) is type(new):
            out |= changed_fields(old, new, f"{prefix}{f.name}.")
        elif old != new:
            out[prefix + f.name] = new
    return out


def set_refusal(argv: list[str]) -> str | None:
    """The one line refusing the retired `--set FIELD=VALUE ...` (None without it): what was
    given, then the same settings as flags, e.g. '--set demo_source=paper: write --demo-source paper'."""
    pairs, inside, found = [], False, False
    for arg in argv:
        if arg == "--set" or arg.startswith("--set="):
            found, inside = True, True
            pairs += [arg.split("=", 1)[1]] if "=" in arg else []
        elif arg.startswith("-"):
            inside = False
        elif inside:
            pairs.append(arg)
    if not found:
        return None
    if not pairs:
        return ("--set: write each run-configuration field as a flag, as `ttmjx train` takes it "
                "(e.g. --demo-source paper, --train.members 4)")
    return f"--set {' '.join(pairs)}: write {' '.join(setting_flag(p) for p in pairs)}"


def setting_flag(pair: str) -> str:
    """'demo_source=paper' -> '--demo-source paper'; booleans as tyro's switches
    ('practice=false' -> '--no-practice', 'world.timing.ideal_timing=true' -> '--world.timing.ideal-timing')."""
    key, _, value = pair.partition("=")
    key = key.replace("_", "-")
    head, dot, last = key.rpartition(".")
    if value.lower() in ("true", "false"):
        return f"--{head}{dot}{'' if value.lower() == 'true' else 'no-'}{last}"
    return f"--{key} {value}" if value else f"--{key}"


def flags_of(changed: dict) -> list[str]:
    """{dotted field: value} (changed_fields) as the flags that set them, in order:
    {'demo_source': 'paper', 'practice': False} -> ['--demo-source', 'paper', '--no-practice']."""
    out = []
    for key, value in changed.items():
        head, dot, last = key.replace("_", "-").rpartition(".")
        if isinstance(value, bool):
            out.append(f"--{head}{dot}{'' if value else 'no-'}{last}")
        else:
            values = value if isinstance(value, (tuple, list)) else (value,)
            out += [f"--{head}{dot}{last}", *map(str, values)]
    return out
