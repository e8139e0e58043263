"""What `ttmjx robot serve` serves: the station's world, contract and timing, from an export
(its training world and the timing it was trained under, checked) or, without one, from the
default World at a control rate and a timing profile."""
from __future__ import annotations

from typing import NamedTuple

from ttmjx.world.config import Timing, World


class Served(NamedTuple):
    cfg: World               # the station's world (throws included)
    contract: object         # deploy.robot.contract.Contract the runner must match
    timing: Timing
    timing_info: dict | None   # the summary's `timing` (an export's range check); None without one


def served_station(policy: str | None, distribution: str | None, control_hz: int | None, timing: str | None,
                   allow_untrained_timing: bool = False) -> Served:
    """The station for `policy` (an export directory: its world and trained timing; a timing
    outside the trained ranges is a TimingError unless allowed), or without one the default World
    at `control_hz` (None: its own) under the profile `timing` (None: nominal; TimingError naming
    the profiles if unknown). `distribution` replaces the throws (None: the world's)."""
    from deploy.robot.contract import contract_from_world
    if policy is not None:
        from deploy.sim.station import load_for_station, resolve_timing
        loaded = load_for_station(policy, distribution)   # its timing record is required
        tm, info = resolve_timing(loaded, timing, allow_untrained_timing)
        return Served(loaded.cfg, loaded.contract, tm, info)
    from deploy.robot.timing_check import profile_timing
    tm = profile_timing(timing)
    cfg = World() if control_hz is None else World(control_hz=control_hz)
    contract = contract_from_world(cfg, cfg.control_hz)
    return Served(cfg.with_throws(distribution) if distribution else cfg, contract, tm, None)
