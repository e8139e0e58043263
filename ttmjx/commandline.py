"""The command line's plumbing, shared by both sides of `ttmjx` (standard library and tyro only,
so the robot's computer runs it without JAX): argument classes whose bounds are checked before
any work, one-line errors with exit codes (2 bad input, 1 a fault of the machine or the work,
130 / 143 after a signal), tyro's boxed errors as one line, the command table's usage and
dispatch, and --json reports.
"""
from __future__ import annotations

import contextlib
import dataclasses
import io
import json
import os
import re
import signal
import sys
from typing import Annotated, Any, Callable, ClassVar, NamedTuple, NoReturn

import tyro

from ttmjx.world.files import json_safe

Flag = Annotated[bool, tyro.conf.FlagCreatePairsOff]   # a bare --flag, off by default


# --------------------------------------------------------------------------------------------
# Arguments: one frozen dataclass per subcommand; field docstrings are the --help lines.
# --------------------------------------------------------------------------------------------
@dataclasses.dataclass(frozen=True, kw_only=True)
class Report:
    json: Flag = False
    """Print one JSON object as the last line (non-finite numbers as null)."""

    # {field: (lowest, highest or None)} checked when the arguments are built, before any work.
    BOUNDS: ClassVar[dict] = {}
    # Fields naming a file or directory this command creates: refused up front if it exists as
    # the other kind (a file where a directory goes, or the reverse).
    NEW_DIRS: ClassVar[tuple] = ()
    NEW_FILES: ClassVar[tuple] = ()

    def __post_init__(self):
        if isinstance(getattr(self, "seed", None), int):
            check_range("seed", self.seed, 0, 2 ** 32 - 1)    # seeds outside wrap onto others
        for name, (low, high) in self.BOUNDS.items():
            check_range(name, getattr(self, name), low, high() if callable(high) else high)
        for name in self.NEW_DIRS:
            check_new_path(name, getattr(self, name), want_dir=True)
        for name in self.NEW_FILES:
            check_new_path(name, getattr(self, name), want_dir=False)


def check_range(name: str, value, low, high) -> None:
    """ValueError naming the flag, the value and the expected range (None values are unset)."""
    if value is None:
        return
    flag = "--" + name.replace("_", "-")
    if isinstance(value, float) and value != value:
        raise ValueError(f"{flag} is NaN; expected a number >= {low}")
    if value < low or (high is not None and value > high):
        expected = f">= {low}" if high is None else f"between {low} and {high}"
        raise ValueError(f"{flag} {value}: expected {expected}")


def check_new_path(name: str, path: str | None, want_dir: bool) -> None:
    flag = "--" + name.replace("_", "-")
    if path is None:
        return
    if want_dir and os.path.isfile(path):
        raise ValueError(f"{flag} {path!r} is a file; expected a new directory")
    if want_dir and os.path.isdir(path) and os.listdir(path):
        raise ValueError(f"{flag} {path!r} already holds files; expected a new or empty directory")
    if not want_dir and os.path.isdir(path):
        raise ValueError(f"{flag} {path!r} is a directory; expected a file path")
    check_writable_parent(flag, path)


def check_writable_parent(flag: str, path: str) -> None:
    """ValueError naming the flag, the path and the nearest existing ancestor where that is no
    writable directory (a file: "Not a directory" / "File exists" from deep inside otherwise)."""
    parent = os.path.dirname(os.path.abspath(path))
    while not os.path.exists(parent):
        parent = os.path.dirname(parent)
    if not os.path.isdir(parent) or not os.access(parent, os.W_OK):
        raise ValueError(f"{flag} {path!r}: cannot write under {parent!r} (not a writable directory)")


def check_resumable_dir(name: str, path: str | None) -> None:
    """A directory a command creates or resumes (train --run-dir, ablate/baseline/robot run --out):
    ValueError naming the flag and the path where it is a file or lies under one."""
    if path is None:
        return
    flag = "--" + name.replace("_", "-")
    if os.path.exists(path) and not os.path.isdir(path):
        raise ValueError(f"{flag} {path!r} is a file; expected a directory (a new one, or one this command "
                         f"wrote before)")
    if not os.path.isdir(path):
        check_writable_parent(flag, path)


def report(args: Report, obj: dict, text: str) -> None:
    """Print `text`, or with --json `obj` as one line of valid JSON (non-finite -> null)."""
    print(json.dumps(json_safe(obj), allow_nan=False) if args.json else text)


def table(obj: dict, skip: tuple = ()) -> str:
    """key  value lines (floats to 4 significant digits)."""
    width = max((len(k) for k in obj), default=0)
    return "\n".join(f"{k:{width}s}  {v:.4g}" if isinstance(v, float) else f"{k:{width}s}  {v}"
                     for k, v in obj.items() if k not in skip)


class Command(NamedTuple):
    args: type                                   # frozen dataclass: its fields are the flags
    run: Callable[[Any], None]                   # does the work and prints
    help: str                                    # one line for `ttmjx --help`
    parse: Callable[[list[str]], Any] | None = None   # instead of tyro on `args`' own defaults
    resumes: bool = True                         # a stopped call keeps its work and the same command goes on



# --------------------------------------------------------------------------------------------
# Parsing and errors
# --------------------------------------------------------------------------------------------
FLAG_PREFIX = {"RunConfig": "--", "TrainConfig": "--train.", "PolicyConfig": "--policy.", "Robot": "--world.robot.",
               "Throws": "--world.throws.", "Timing": "--world.timing."}


def fail(name: str, message: str, code: int = 2) -> NoReturn:
    """One line on stderr and exit `code` (2: bad input; 1: the work itself failed)."""
    if name == "train":            # a config's own message names its field: name the flag
        message = re.sub(r"\b(RunConfig|TrainConfig|PolicyConfig|Robot|Throws|Timing)\.(\w+)=?",
                         lambda m: FLAG_PREFIX[m[1]] + m[2].replace("_", "-") + " ", message)
    # one write: print() writes the line and its newline apart, and another thread may print between
    sys.stderr.write(f"ttmjx{' ' + name if name else ''}: error: {' '.join(message.split())}\n")
    sys.stderr.flush()
    sys.exit(code)


def file_error(e: OSError) -> str:
    """'PATH: cause' of a failed file operation. A write through an open file (numpy's savez, a
    stream) raises without the file's name: it is then the path the project's innermost frame
    was writing (its local `path`, `tmp`, ...), so a full disk always names where."""
    where = e.filename or culprit_path(e.__traceback__)
    return f"{where}: {e.strerror or e}" if where else f"{e.strerror or e}"


PROJECT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))


def culprit_path(tb) -> str | None:
    frames = []
    while tb is not None:
        frames.append(tb.tb_frame)
        tb = tb.tb_next
    for frame in reversed(frames):          # innermost first
        code = os.path.abspath(frame.f_code.co_filename)
        if not code.startswith(PROJECT) or os.sep + "site-packages" + os.sep in code:
            continue
        for name in ("path", "tmp", "filename", "file", "out", "out_dir", "directory", "run_dir"):
            value = frame.f_locals.get(name)
            if isinstance(value, str) and value:
                return value
    return None


def one_line(box: str) -> str:
    """tyro's boxed error as one line: the message section, without the title ('Value error'),
    borders, rules, colours or the closing 'For full helptext' hint (rich draws the box in
    unicode on a terminal and in ASCII when the streams are captured)."""
    sections, current = [], []
    for line in re.sub(r"\x1b\[[0-9;]*m", "", box).splitlines():
        line = line.strip()
        if line.startswith(("╭", "╰")):
            continue
        line = line.strip("│|").strip()
        if line and set(line) <= set("─-━═+"):
            sections.append(current)
            current = []
        elif line:
            current.append(line)
    sections.append(current)
    if "╭" not in box:
        sections = sections[1:]          # the ASCII box's title ('Value error') above its first rule
    sections = [s for s in sections if s and not s[0].startswith("For full helptext")]
    text = " ".join(sections[0]) if sections else ""
    # A bound checked by an argument class or a config: tyro prefixes its message with where.
    return re.sub(r"^Error parsing [\w.]+: ", "", text) or box


def parse_args(name: str, cls: type, argv: list[str], default: Any = None) -> Any:
    """tyro on `cls` (starting from `default` if given); a parse error exits 2 with one line."""
    err = io.StringIO()
    try:
        with contextlib.redirect_stderr(err):
            args = tyro.cli(cls, args=argv, prog=f"ttmjx {name}",
                            **({} if default is None else {"default": default}))
    except SystemExit as e:
        if e.code == 2:
            fail(name, one_line(err.getvalue()))
        sys.stderr.write(err.getvalue())
        raise
    sys.stderr.write(err.getvalue())
    return args


def usage(commands: dict, group: str = "") -> str:
    names = [n for n in commands if n.startswith(group)]
    width = max(map(len, names))
    return "\n".join([f"usage: ttmjx {group or 'COMMAND'}{' COMMAND' if group else ''} [--help] [OPTIONS]",
                      "", "commands:", *(f"  {n:{width}s}  {commands[n].help}" for n in names), "",
                      "`ttmjx COMMAND --help` lists every option with its type, default and meaning."])


def command_of(commands: dict, argv: list[str]) -> tuple[str, list[str]]:
    """(subcommand name, its arguments); `ttmjx [GROUP] --help` prints the table and exits."""
    for k in (2, 1):
        if " ".join(argv[:k]) in commands:
            return " ".join(argv[:k]), argv[k:]
    group = argv[0] if argv and any(n.startswith(argv[0] + " ") for n in commands) else ""
    rest = argv[1:] if group else argv
    if rest[:1] in (["-h"], ["--help"]):
        print(usage(commands, group))
        sys.exit(0)
    expected = ", ".join(n.removeprefix(group).strip() for n in commands if n.startswith(group))
    fail(group, f"{'unknown command ' + repr(rest[0]) if rest else 'no command'}; expected one of {expected}")


# --------------------------------------------------------------------------------------------
# Signals: the one home of both ways a command stops on SIGINT (Ctrl-C) or SIGTERM
#   - anywhere in a command, the signal unwinds it: Ctrl-C raises KeyboardInterrupt (Python's
#     own), SIGTERM raises Stopped (stop_on_sigterm); `run` ends both as one line, 130 / 143;
#   - inside the training loop (training/trainer.py Run), where an
#     exception would lose the iteration and could cut a checkpoint in half, the signal only asks
#     the loop to stop (install_stop_signals): it finishes the iteration, saves, and returns the
#     signal as `stopped_by_signal`, which the command exits with (signal_exit_code).
# --------------------------------------------------------------------------------------------
def signal_exit_code(signum: int) -> int:
    """128 + signal: the shell's convention for a command ended by a signal (130 Ctrl-C, 143 SIGTERM)."""
    return 128 + signum


def install_stop_signals(owner) -> None:
    """SIGINT/SIGTERM set owner._stop to the signal (the loop saves and exits after the iteration,
    logging through owner.log); a second one exits at once (the last checkpoint stays).
    restore_signals puts the previous handlers back."""

    def handler(signum, frame):
        if owner._stop:
            os._exit(signal_exit_code(signum))
        owner._stop = signum
        owner.log(f"\n[ttmjx] {signal.Signals(signum).name}: finishing this iteration, saving a checkpoint, "
                  f"then exiting (resume with the same command)")
    owner._old = {s: signal.signal(s, handler) for s in (signal.SIGINT, signal.SIGTERM)}


def restore_signals(owner) -> None:
    """The handlers install_stop_signals replaced, back in place."""
    for s, h in getattr(owner, "_old", {}).items():
        signal.signal(s, h)


class Stopped(BaseException):
    """SIGTERM outside a training loop (whose own handler saves a checkpoint and stops it at the
    end of the iteration, training/trainer.py): the command ends as after Ctrl-C, with 143."""
    def __init__(self, signum: int):
        super().__init__(signum)
        self.signum = signum


@contextlib.contextmanager
def stop_on_sigterm():
    """SIGTERM raises Stopped (a KeyboardInterrupt's counterpart) while the command runs, so it
    unwinds like Ctrl-C: outputs written through a temporary name stay whole or absent, what was
    saved (checkpoints, episode logs) stays, and main exits 143 with one line. A stop raised
    where Python drops exceptions (a collector or weakref callback, a finalizer: JAX has them)
    is sent again (`resent`)."""
    import threading
    if threading.current_thread() is not threading.main_thread():
        yield
        return

    def handler(signum, frame):
        raise Stopped(signum)
    old, old_hook = signal.signal(signal.SIGTERM, handler), sys.unraisablehook
    sys.unraisablehook = lambda u: resent(u) or old_hook(u)
    try:
        yield
    finally:
        signal.signal(signal.SIGTERM, old)
        sys.unraisablehook = old_hook


def resent(unraisable) -> bool:
    """If a dropped exception (sys.unraisablehook's argument) is a stop, send its signal again
    10 ms later, when the callback is over, and return True; else False."""
    import threading
    e = unraisable.exc_value
    signum = e.signum if isinstance(e, Stopped) else signal.SIGINT if isinstance(e, KeyboardInterrupt) else None
    if signum is None:
        return False
    timer = threading.Timer(0.01, os.kill, (os.getpid(), signum))
    timer.daemon = True
    timer.start()
    return True


def after_stop(cmd: Command) -> str:
    """What a stopped call of `cmd` leaves, and what to do next."""
    if cmd.resumes:
        return "what was saved is kept: run the same command to resume"
    return "it keeps no partial output: run the same command again"


def run(commands: dict, argv: list[str], prepare: Callable[[], None] | None = None) -> None:
    """Parse and run the subcommand `argv` names; every failure ends as one line and its exit
    code. `prepare` runs before parsing (e.g. JAX's distributed start, which presets need)."""
    name, rest = command_of(commands, argv)
    cmd = commands[name]
    try:
        with stop_on_sigterm():
            if prepare is not None:
                prepare()
            args = cmd.parse(rest) if cmd.parse else parse_args(name, cmd.args, rest)
            cmd.run(args)
    except Stopped:
        fail(name, f"stopped by SIGTERM; {after_stop(cmd)}", code=signal_exit_code(signal.SIGTERM))
    except (ValueError, FileExistsError, FileNotFoundError, NotADirectoryError, IsADirectoryError) as e:
        fail(name, str(e) if not isinstance(e, OSError) or not e.strerror else file_error(e))
    except OSError as e:          # permission denied, disk full: the environment, not the input
        fail(name, file_error(e), code=1)
    except (RuntimeError, ArithmeticError) as e:   # e.g. training.trainer.NonFiniteError
        fail(name, f"{type(e).__name__}: {e}", code=1)
    except KeyboardInterrupt:
        fail(name, f"stopped by SIGINT (Ctrl-C); {after_stop(cmd)}", code=signal_exit_code(signal.SIGINT))
