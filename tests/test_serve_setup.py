"""`ttmjx robot serve` without an export (deploy/sim/serve_setup.py): the default World at the
asked control rate, its contract, the throws asked for, and a timing profile by name (nominal by
default; an unknown name refused naming the profiles). With an export: tests/test_timing_contract.py."""
import pytest

from deploy.robot.timing_check import TIMING_PROFILES, TimingError
from deploy.sim.serve_setup import served_station


def test_without_an_export_the_default_world_at_the_asked_rate_and_profile():
    served = served_station(None, "any", 60, None)
    assert served.cfg.control_hz == 60 and served.contract.control_hz == 60 and served.cfg.throws.name == "any"
    assert served.timing == TIMING_PROFILES["nominal"] and served.timing_info is None
    assert served_station(None, None, None, "zero").timing == TIMING_PROFILES["zero"]
    with pytest.raises(TimingError, match="unknown station timing profile 'fast'; expected one of zero, nominal"):
        served_station(None, None, None, "fast")
