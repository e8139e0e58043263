"""Where a run's arrays live: a mesh of the run's devices and the placement of every part.

One code path for 1..D devices (one device is the mesh of shape (1, 1)). The mesh has two axes:

* ``member``: ensemble members (the leading [N] axis of the weights, Adam moments and moving
  average) are split over it, N / m whole members per group of devices;
* ``batch``: the devices that share a member split its practice throws and its training
  windows; the gradient of a member is summed over them (XLA inserts the all-reduce).

Its shape is (m, D / m) with m = min(N, D): N a multiple of D puts N / D whole members on every
device (no collective in an update), D a multiple of N spreads each member over D / N devices.
Other counts cannot be placed evenly and are refused. The cache (the data pool) is replicated:
every device samples its windows from its own copy, so no update moves pool rows between
devices; a round all-gathers only its M new episodes (docs/SCALING.md). The key and the
counters are replicated too.
"""
from __future__ import annotations

import os
from typing import NamedTuple

import jax
import numpy as np
from jax.sharding import AxisType, Mesh, NamedSharding, PartitionSpec as P

from training.runconfig import RunConfig

MEMBER, BATCH, LANE = "member", "batch", "lane"


class Layout(NamedTuple):
    """The mesh of a run and the shardings of its parts. `free`: the code of one lane inside a
    program over lanes (training.seeds), which places nothing itself: the lanes' mesh does."""
    mesh: Mesh
    free: bool = False

    @property
    def member_axis(self) -> str | None:
        """The mesh axis the vmapped members map to (None inside a lane)."""
        return None if self.free else MEMBER

    def sharding(self, *spec) -> NamedSharding:
        """NamedSharding of PartitionSpec(*spec) on this mesh."""
        return NamedSharding(self.mesh, P(*spec))

    @property
    def replicated(self) -> NamedSharding:
        """A whole copy on every device (cache, key, counters, scalars)."""
        return self.sharding()

    @property
    def members(self) -> NamedSharding:
        """Leading [N] axis split over `member` (weights, optimizer state, moving average)."""
        return self.sharding(MEMBER)

    @property
    def throws(self) -> NamedSharding:
        """Leading [M] axis of a round's throws split over every device: the M throws are N
        contiguous blocks, one per member, so a device plays throws of the members it holds."""
        return self.sharding((MEMBER, BATCH))

    def constrain_batch(self, tree):
        """Split the leading [B] axis of a member's windows over `batch`. Use inside
        `jax.vmap(..., spmd_axis_name=MEMBER)`, which adds the member axis in front."""
        return tree if self.free else jax.lax.with_sharding_constraint(tree, self.sharding(BATCH))

    def constrain_throws(self, tree):
        """Split the leading [M] axis over the devices (inside jit)."""
        return tree if self.free else jax.lax.with_sharding_constraint(tree, self.throws)

    def put(self, tree, shardings):
        """`tree` placed as `shardings` (a pytree prefix of it). A mesh that spans several
        processes (the within-run layout) gets every process's shards built from the same host
        value (same seed, same files), so nothing crosses processes (device_put would all-gather
        the whole pool to check that the processes agree)."""
        if not self.mesh.is_multi_process:
            return jax.device_put(tree, shardings)
        host = jax.device_get(tree)

        def shards(sharding, sub):
            return jax.tree.map(lambda x: jax.make_array_from_callback(np.shape(x), sharding,
                                                                       lambda index: np.asarray(x)[index]), sub)
        return jax.tree.map(shards, shardings, host)

    def local(self, tree):
        """The whole value of every array on this process's first device: for the parts that
        run on the host (MuJoCo C physics) and for evaluation."""
        if self.mesh.is_multi_process:
            from jax.experimental import multihost_utils
            tree = multihost_utils.process_allgather(tree, tiled=True)
        return jax.device_put(tree, jax.local_devices()[0])


def mesh_shape(members: int, devices: int, available: int | None = None) -> tuple[int, int]:
    """(m, b) with m * b = devices: m groups along `member`, b devices along `batch`."""
    if members % devices == 0:
        return devices, 1
    if devices % members == 0:
        return members, devices // members
    fits = ", ".join(map(str, fitting_devices(members, available or devices)))
    raise ValueError(f"train.members={members} cannot be placed on {devices} devices: one count must divide the "
                     f"other (--devices {fits})")


def fitting_devices(members: int, available: int) -> list[int]:
    """Device counts up to `available` on which `members` members can be placed."""
    return [d for d in range(1, available + 1) if members % d == 0 or d % members == 0]


def device_count(requested: int | None, available: int) -> int:
    """The run's device count: `requested` (None: all), refused beyond what is available."""
    if requested is None:
        return available
    if requested > available:
        raise ValueError(f"devices={requested} but only {available} {jax.default_backend()} device(s) are available")
    if jax.process_count() > 1 and requested != available:
        raise ValueError(f"devices={requested}: a run over {jax.process_count()} processes uses all "
                         f"{available} devices (leave --devices unset)")
    return requested


def check_split(members: int, batch_devices: int, episodes: int | None, batch_size: int, devices: int) -> None:
    """Refuse a round (`episodes` throws; None: no practice) or a batch that the devices sharing a
    member cannot split evenly."""
    per_member = (episodes or 0) // members
    if per_member % batch_devices:
        raise ValueError(f"episodes_per_ssp={episodes} gives each of train.members={members} members {per_member} "
                         f"throws, which {batch_devices} devices (of {devices}) cannot split evenly")
    if batch_size % batch_devices:
        raise ValueError(f"train.batch_size={batch_size} cannot be split evenly over the {batch_devices} devices "
                         f"(of {devices}) that share each of train.members={members} members")


def make_layout(cfg: RunConfig) -> Layout:
    """The layout of a run on cfg.devices devices, checked before anything is compiled:
    ValueError (one line, with the counts) for more devices than there are, or members,
    practice throws or training windows that cannot be placed evenly."""
    available = jax.device_count()
    n = device_count(cfg.devices, available)
    members = cfg.train.members
    m, b = mesh_shape(members, n, available)
    check_split(members, b, cfg.episodes_per_ssp if cfg.practice else None, cfg.train.batch_size, n)
    return _layout(m, b)


def single_device() -> Layout:
    """The mesh of one device (the default device): what a run on one device uses."""
    return _layout(1, 1)


def one_device(device) -> Layout:
    """The mesh of one given device: where a lane's state is built before the lanes of its block
    are stacked there (training.seeds)."""
    return Layout(jax.make_mesh((1, 1), (MEMBER, BATCH), (AxisType.Auto, AxisType.Auto), devices=[device]))


def lane_layout(lanes: int, devices: int | None = None) -> Layout:
    """The layout of a program over `lanes` independent runs (training.seeds): a 1-D mesh
    (`lane`) over `devices` devices (None: every local device, at most one per lane), each device
    the lanes of its block; inside a lane nothing is placed (`free`). ValueError (one line, with
    the counts) for more devices than there are."""
    available = check_local_devices(devices)
    n = min(lanes, available) if devices is None else devices
    return Layout(jax.make_mesh((n,), (LANE,), (AxisType.Auto,), devices=jax.local_devices()[:n]), free=True)


def check_local_devices(devices: int | None) -> int:
    """The local device count; ValueError (one line) if `devices` asks for more."""
    available = jax.local_device_count()
    if devices is not None and devices > available:
        raise ValueError(f"--devices {devices} but only {available} {jax.default_backend()} device(s) are available")
    return available


def process_lanes(lanes: int, processes: int | None = None, index: int | None = None) -> tuple[int, int]:
    """[lo, hi): the block of `lanes` that this process trains (jax.process_index() of
    jax.process_count(), or `index` of `processes`). Lanes share nothing, so each process trains
    its block on its own devices and no array spans processes; the blocks are as even as the
    counts allow (the first lanes % processes blocks one longer). ValueError when some process
    would get no lane."""
    processes = jax.process_count() if processes is None else processes
    index = jax.process_index() if index is None else index
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


def _layout(m: int, b: int) -> Layout:
    # Auto axes: shardings propagate from the placed inputs and the constraints (no explicit
    # sharding in the types), so the per-member code is the same on any mesh.
    return Layout(jax.make_mesh((m, b), (MEMBER, BATCH), (AxisType.Auto, AxisType.Auto),
                                devices=jax.devices()[:m * b]))


# -- several processes (hosts) -----------------------------------------------------------------
# Launchers that start one process per host and say how many there are.
PROCESS_COUNTS = ("SLURM_NTASKS", "OMPI_COMM_WORLD_SIZE")


def distributed_settings(environ) -> dict | None:
    """Arguments for jax.distributed.initialize from the environment; None: a one-process run.

    JAX_COORDINATOR_ADDRESS (host:port of process 0) with JAX_NUM_PROCESSES and JAX_PROCESS_ID,
    or a launcher that JAX detects by itself (SLURM, Open MPI) reporting more than one process."""
    if environ.get("JAX_COORDINATOR_ADDRESS"):
        named = {"num_processes": "JAX_NUM_PROCESSES", "process_id": "JAX_PROCESS_ID"}
        return {"coordinator_address": environ["JAX_COORDINATOR_ADDRESS"],
                **{arg: int(environ[var]) for arg, var in named.items() if environ.get(var)}}
    if any(int(environ.get(var) or 1) > 1 for var in PROCESS_COUNTS):
        return {}
    return None


def is_primary() -> bool:
    """Process 0: the one that writes the run's logs and bookkeeping files."""
    return jax.process_index() == 0


def barrier(name: str) -> None:
    """Every process waits here for the others (a no-op with one process)."""
    if jax.process_count() > 1:
        from jax.experimental import multihost_utils
        multihost_utils.sync_global_devices(name)


def initialize_distributed(environ=None) -> bool:
    """jax.distributed.initialize() when the environment describes a multi-process run (it
    must come before JAX's first computation); returns whether it was called."""
    settings = distributed_settings(os.environ if environ is None else environ)
    if settings is None or jax.distributed.is_initialized():
        return False
    jax.distributed.initialize(**settings)
    return True
