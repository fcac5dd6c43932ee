"""The seed axis on devices: a 1-d mesh over every device of every process, seeds padded to a multiple of its size.

Each seed's run is independent of the others, so the vmapped program splits along seeds with no communication: the
same compiled chunk runs on one CPU, on the host devices of a CPU (``--host-devices``), on 8 GPUs, or across hosts
(``jax.distributed``). Padding seeds (``seed_start + seeds`` onwards) train like any other and are dropped from every
result; they only make the seed count divisible by the number of devices.
"""

from __future__ import annotations

import dataclasses
from typing import Any

import jax
import numpy as np
from jax.experimental import multihost_utils
from jax.sharding import Mesh, NamedSharding, PartitionSpec

AXIS = "seeds"


@dataclasses.dataclass(frozen=True)
class SeedLayout:
    """Where the seeds of one run live: ``seeds`` real ones, padded to a multiple of the mesh's size."""

    seeds: int
    mesh: Mesh

    @property
    def devices(self) -> int:
        """Devices the seed axis spans (over all processes)."""
        return self.mesh.size

    @property
    def padded(self) -> int:
        """Seeds trained: ``seeds`` rounded up to a multiple of ``devices``."""
        return -(-self.seeds // self.devices) * self.devices

    @property
    def sharding(self) -> NamedSharding:
        """Leading (seed) axis split over the mesh, every other axis whole."""
        return NamedSharding(self.mesh, PartitionSpec(AXIS))

    def to_host(self, tree: Any) -> Any:
        """NumPy copies of the real seeds' values of a tree of seed-leading arrays, on every process."""
        return jax.tree.map(lambda x: _gather(x)[: self.seeds], tree)

    def place(self, tree: Any) -> Any:
        """A tree of host arrays with ``padded`` leading seeds as arrays sharded like the chunk's inputs (on every
        process, each process providing its own devices' shards)."""
        return jax.tree.map(lambda x: place(x, self.sharding), tree)


def place(host: np.ndarray, sharding: jax.sharding.Sharding) -> jax.Array:
    """A host array as a jax.Array laid out by ``sharding`` (each process providing its own devices' shards)."""
    return jax.make_array_from_callback(host.shape, sharding, lambda index: host[index])


def seed_layout(seeds: int, devices: list[Any] | None = None) -> SeedLayout:
    """The layout of ``seeds`` seeds over ``devices`` (default: every device of every process)."""
    return SeedLayout(seeds, Mesh(np.array(devices or jax.devices()), (AXIS,)))


def _gather(x: Any) -> np.ndarray:
    """The whole array on this host (collected from the other processes when it spans several)."""
    if isinstance(x, jax.Array) and not x.is_fully_addressable:
        return np.asarray(multihost_utils.process_allgather(x, tiled=True))
    return np.asarray(x)


def is_primary() -> bool:
    """Whether this process writes the results (the only one, or process 0 of a multi-host run)."""
    return jax.process_index() == 0


def sync(name: str) -> None:
    """Wait until every process gets here (a no-op in a single-process run)."""
    if jax.process_count() > 1:
        multihost_utils.sync_global_devices(name)
