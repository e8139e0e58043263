"""Where the lanes of a training program live: a one-axis mesh (`lane`) of local devices, each
device the lanes of its block (training.trainer), and, with several processes, which block of
lanes each process trains.

Lanes share nothing (each has its own weights, optimizer state, moving average, pool, key and
counters), so no compiled step has a collective: jit's partitioner splits every lane-stacked
array along `lane` and each device computes its block alone (tests/test_sharding.py checks the
compiled programs). One seed is a lane of one, on one device. A lane count the devices do not
divide is padded with copies of the last lane (computed, never written).

Splitting one run over devices (its members over a `member` axis, its windows over `batch`) was
built and measured first: 2 H200s ran a paper-sim-new round 1.05x faster than one (a round is
latency-bound: 1,600 sequential physics steps per episode), so it was removed (docs/SCALING.md).
"""
from __future__ import annotations

import os
from typing import NamedTuple

import jax
from jax.sharding import AxisType, Mesh, NamedSharding, PartitionSpec as P

LANE = "lane"


class Layout(NamedTuple):
    """The mesh of a program's lanes."""
    mesh: Mesh

    def sharding(self, *spec) -> NamedSharding:
        """NamedSharding of PartitionSpec(*spec) on this mesh."""
        return NamedSharding(self.mesh, P(*spec))

    @property
    def lanes(self) -> NamedSharding:
        """The leading [L] axis split over the devices, a block of lanes each."""
        return self.sharding(LANE)


def lane_layout(lanes: int, devices: int | None = None) -> Layout:
    """The layout of a program over `lanes` independent runs (training.trainer): a 1-D mesh
    (`lane`) over `devices` local devices (None: every local device, at most one per lane), each
    device the lanes of its block. ValueError (one line, with the counts) for more devices than
    there are."""
    available = check_local_devices(devices)
    n = min(lanes, available) if devices is None else devices
    return Layout(jax.make_mesh((n,), (LANE,), (AxisType.Auto,), devices=jax.local_devices()[:n]))


def check_local_devices(devices: int | None) -> int:
    """The local device count; ValueError (one line) if `devices` asks for more."""
    available = jax.local_device_count()
    if devices is not None and devices > available:
        raise ValueError(f"--devices {devices} but only {available} {jax.default_backend()} device(s) are available")
    return available


def process_lanes(lanes: int, processes: int | None = None, index: int | None = None) -> tuple[int, int]:
    """[lo, hi): the block of `lanes` that this process trains (launcher_process(), or `index` of
    `processes`). Lanes share nothing, so each process trains its block on its own devices as a
    program of its own; the blocks are as even as the counts allow (the first lanes % processes
    blocks one longer). ValueError when some process would get no lane."""
    here, count = launcher_process()
    processes = count if processes is None else processes
    index = here if index is None else index
    if lanes < processes:
        raise ValueError(f"{lanes} lane(s) over {processes} processes: every process needs at least one lane "
                         f"(train more seeds or arms, or start fewer processes)")
    size, extra = divmod(lanes, processes)
    lo = index * size + min(index, extra)
    return lo, lo + size + (index < extra)


def padded_lanes(lanes: int, devices: int) -> int:
    """Lanes rounded up to a multiple of the devices: each device computes an equal block (the
    extra lanes repeat the last real one and are never written)."""
    return -(-lanes // devices) * devices


# -- several processes (hosts) -----------------------------------------------------------------
# (index, count) variables of the launchers that start one process per host: jax.distributed's
# own names first, then SLURM's and Open MPI's (the ones jax.distributed detects).
LAUNCHERS = (("JAX_PROCESS_ID", "JAX_NUM_PROCESSES"), ("SLURM_PROCID", "SLURM_NTASKS"),
             ("OMPI_COMM_WORLD_RANK", "OMPI_COMM_WORLD_SIZE"))


def launcher_process(environ=None) -> tuple[int, int]:
    """(this process's index, the process count) that the launcher set in the environment:
    (0, 1) for a single process. ValueError (one line) for an index outside the count.

    A program over lanes needs nothing from the other processes (no collective, no shared
    array), so processes are not joined by jax.distributed: its global job would make every
    Orbax save a collective over all processes and write each array from process 0, where each
    lane's checkpoint belongs to the one process that trains it (docs/SCALING.md)."""
    env = os.environ if environ is None else environ
    for index_var, count_var in LAUNCHERS:
        if env.get(count_var):
            count, index = int(env[count_var]), int(env.get(index_var) or 0)
            if not 0 <= index < count:
                raise ValueError(f"{index_var}={index} with {count_var}={count}: expected 0..{count - 1}")
            return index, count
    return 0, 1


def is_primary() -> bool:
    """Process 0 of the launcher: the one that writes a batch's seeds.json (each lane's directory
    is written by the process that trains it)."""
    return launcher_process()[0] == 0
