"""The cell configuration (TOML): where each device is and how it is spoken to.

Both sides read the same file: the drivers (`ttmjx robot run --station cell --config F`) and the
rehearsal server (`ttmjx robot serve --config F`), so a rehearsal exercises the addresses and
register map the real cell will use. deploy/robot/drivers/cell.example.toml documents every key.
"""
from __future__ import annotations

import dataclasses
import math
import socket
import tomllib

MAX_STALE_S = 0.25          # s, the longest stale limit of a part (deploy/robot/drivers/cell.py)
EGM_CYCLE_S = 0.004         # s, the controller's EGM message period (250 Hz; docs/ROBOT.md)


def sample_ages(trained) -> tuple[list[tuple[float, str]], dict]:
    """([(seconds, 'joint' | 'ball')], {kind: why}): the oldest the cell's newest sample gets
    when it runs as designed, and why. Joints: one EGM cycle (stamped at receipt; the gantry is
    read at the arm's stamp, deploy/robot/drivers/cell.py). Ball: one tracker period plus the top
    of the latency and jitter the export was trained under (`trained`: its contract's timing
    model, a Timing), the timing the cell must keep for the policy; none where it was trained
    seeing the ball every physics step (no tracker rate)."""
    ages = [(EGM_CYCLE_S, "joint")]
    why = {"joint": f"(one EGM cycle at {1 / EGM_CYCLE_S:g} Hz, stamped at receipt)"}
    if trained.tracker_hz:
        latency = trained.tracker_latency_s + trained.spreads()[0]
        ages.append((1.0 / trained.tracker_hz + latency + trained.jitter_s, "ball"))
        why["ball"] = (f"when its tracker runs as the export was trained ({trained.tracker_hz:g} Hz, latency up to "
                       f"{latency * 1e3:.3g} ms, jitter up to {trained.jitter_s * 1e3:.3g} ms)")
    return ages, why


@dataclasses.dataclass(frozen=True)
class EgmConfig:
    port: int = 6510            # this computer's UDP port; the controller sends to it
    host: str = "127.0.0.1"     # this computer's address as the controller knows it (serve sends here)
    stale_s: float = 0.1        # no controller message for this long: logged (the runner holds)


@dataclasses.dataclass(frozen=True)
class Registers:
    """Holding-register addresses (0-based) of the gantry drive; positions are int32 in two
    registers (word order `word_order`), scaled by `counts_per_m`."""
    target_x: int = 0           # int32, counts
    target_y: int = 2           # int32, counts
    velocity: int = 4           # uint16, mm/s: the fixed positioning velocity
    control: int = 5            # uint16: bit 0 enable, bit 1 new setpoint (toggled per target)
    actual_x: int = 10          # int32, counts
    actual_y: int = 12          # int32, counts
    status: int = 14            # uint16: bit 0 ready, bit 1 fault, bit 2 setpoint acknowledged
    counts_per_m: float = 1e6   # position counts per metre (1 count = 1 um)
    word_order: str = "big"     # int32 high word first ("big") or low word first ("little")

    @property
    def span(self) -> int:
        """Registers from 0 up to the last one used (the rehearsal server's block size)."""
        return max(self.target_x + 2, self.target_y + 2, self.velocity + 1, self.control + 1,
                   self.actual_x + 2, self.actual_y + 2, self.status + 1)


@dataclasses.dataclass(frozen=True)
class GantryConfig:
    host: str = "127.0.0.1"
    port: int = 502
    device_id: int = 1
    poll_hz: float = 100.0      # feedback reads per second (the drive answers at up to 100 Hz)
    velocity_m_s: float = 1.0   # the fixed positioning velocity of every target
    timeout_s: float = 0.05     # one Modbus transaction
    stale_s: float = 0.1        # no reading for this long: the Robot's feedback freezes (HOLD)
    # The link's latency compensation (deploy/robot/drivers/lead.py): each target is led by the
    # link's one-way latency above the arm's own (forward_share x the median round trip).
    compensate_latency: bool = True     # false: targets sent as given (comparisons only)
    forward_share: float = 0.5  # of the round trip, on the way to the drive (0.5: a symmetric link)
    registers: Registers = Registers()


@dataclasses.dataclass(frozen=True)
class TrackerConfig:
    port: int = 6520            # this computer's UDP port; the tracker sends to it
    host: str = "127.0.0.1"     # this computer's address as the tracker knows it (serve sends here)
    offset_s: float = 0.0       # runner time = tracker time + offset_s


@dataclasses.dataclass(frozen=True)
class LauncherConfig:
    """The rehearsal server's launcher and referee (JSON lines over TCP); a real cell without a
    launcher leaves the section out and throws by hand."""
    host: str = "127.0.0.1"
    port: int = 6530


@dataclasses.dataclass(frozen=True)
class CellConfig:
    egm: EgmConfig = EgmConfig()
    gantry: GantryConfig = GantryConfig()
    tracker: TrackerConfig = TrackerConfig()
    launcher: LauncherConfig | None = None


SECTIONS = {"egm": EgmConfig, "gantry": GantryConfig, "tracker": TrackerConfig,
            "launcher": LauncherConfig}


def _build(cls, table: dict, where: str):
    """cls(**table) with every key and value checked (unknown keys, wrong types, bad ranges)."""
    if not isinstance(table, dict):
        raise ValueError(f"{where}: expected a table, got {table!r}")
    fields = {f.name: f for f in dataclasses.fields(cls)}
    values = {}
    for key, value in table.items():
        if key not in fields:
            raise ValueError(f"{where}.{key}: unknown key; expected one of {', '.join(fields)}")
        default = getattr(cls(), key)
        if key == "registers":
            values[key] = _build(Registers, value, f"{where}.registers")
            continue
        if isinstance(default, bool) != isinstance(value, bool) or not isinstance(value, (type(default), int)):
            raise ValueError(f"{where}.{key} = {value!r}: expected a {type(default).__name__}")
        values[key] = type(default)(value)
    out = cls(**values)
    _check(out, where)
    return out


def _check(obj, where: str) -> None:
    for f in dataclasses.fields(obj):
        v = getattr(obj, f.name)
        if f.name == "port" and not 1 <= v <= 65535:
            raise ValueError(f"{where}.port = {v}: expected a port between 1 and 65535")
        if f.name in ("stale_s", "poll_hz", "velocity_m_s", "timeout_s", "counts_per_m") and not (
                math.isfinite(v) and v > 0):
            raise ValueError(f"{where}.{f.name} = {v}: expected a finite number > 0")
        if f.name == "forward_share" and not (math.isfinite(v) and 0 < v <= 1):
            raise ValueError(f"{where}.forward_share = {v}: expected a share of the round trip in (0, 1]")
        if f.name == "offset_s" and not math.isfinite(v):
            raise ValueError(f"{where}.offset_s = {v}: expected a finite number")
        if f.name == "word_order" and v not in ("big", "little"):
            raise ValueError(f"{where}.word_order = {v!r}: expected 'big' or 'little'")
        if isinstance(obj, Registers) and isinstance(v, int) and not 0 <= v <= 65533:
            raise ValueError(f"{where}.{f.name} = {v}: expected a register address 0..65533")
    if isinstance(obj, GantryConfig) and not 0 <= obj.device_id <= 247:
        raise ValueError(f"{where}.device_id = {obj.device_id}: expected 0..247")
    if isinstance(obj, (GantryConfig, EgmConfig)) and obj.stale_s > MAX_STALE_S:
        # the cell's Robot joins the arm's recent messages (0.25 s of them) to the gantry's
        # reading: staler than that, a join would have no arm sample to read (drivers/cell.py)
        raise ValueError(f"{where}.stale_s = {obj.stale_s}: expected at most {MAX_STALE_S} s")


def cell_config_from_dict(doc: dict, where: str = "cell config") -> CellConfig:
    for key in doc:
        if key not in SECTIONS:
            raise ValueError(f"{where}: unknown section [{key}]; expected {', '.join(SECTIONS)}")
    return CellConfig(**{k: _build(SECTIONS[k], doc[k], f"{where} [{k}]") for k in doc})


def load_cell_config(path: str) -> CellConfig:
    """The CellConfig of a TOML file; ValueError naming the file and the bad key."""
    try:
        with open(path, "rb") as f:
            doc = tomllib.load(f)
    except FileNotFoundError:
        raise ValueError(f"--config {path!r}: no such file (a cell config, see "
                         f"deploy/robot/drivers/cell.example.toml)") from None
    except tomllib.TOMLDecodeError as e:
        raise ValueError(f"--config {path!r}: not valid TOML ({e})") from None
    return cell_config_from_dict(doc, path)


def to_toml(cfg: CellConfig) -> str:
    """The TOML text of cfg (tests and `serve` write configs with the ports they chose)."""
    lines = []
    for name in SECTIONS:
        sec = getattr(cfg, name)
        if sec is None:
            continue
        lines.append(f"[{name}]")
        nested = []
        for f in dataclasses.fields(sec):
            v = getattr(sec, f.name)
            if dataclasses.is_dataclass(v):
                nested.append((f.name, v))
            else:
                lines.append(f"{f.name} = {_toml_value(v)}")
        for sub, v in nested:
            lines.append(f"[{name}.{sub}]")
            lines += [f"{g.name} = {_toml_value(getattr(v, g.name))}" for g in dataclasses.fields(v)]
    return "\n".join(lines) + "\n"


def _toml_value(v) -> str:
    if isinstance(v, bool):
        return "true" if v else "false"
    if isinstance(v, str):
        return '"' + v.replace("\\", "\\\\").replace('"', '\\"') + '"'
    return repr(v)


def free_port(kind: int) -> int:
    """A port on 127.0.0.1 free now (socket.SOCK_DGRAM or SOCK_STREAM)."""
    s = socket.socket(socket.AF_INET, kind)
    try:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]
    finally:
        s.close()


def loopback_config() -> CellConfig:
    """A cell on this computer (a `serve` rehearsal): every port a free loopback port. The
    gantry link's round trip is all on the way to the drive: serve's link delays the requests
    and answers each at once when carried out (deploy/sim/serve.py, Server.modbus_link)."""
    return CellConfig(egm=EgmConfig(port=free_port(socket.SOCK_DGRAM)),
                      gantry=GantryConfig(port=free_port(socket.SOCK_STREAM), forward_share=1.0),
                      tracker=TrackerConfig(port=free_port(socket.SOCK_DGRAM)),
                      launcher=LauncherConfig(port=free_port(socket.SOCK_STREAM)))
