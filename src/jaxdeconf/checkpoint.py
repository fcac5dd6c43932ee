"""Orbax checkpoints of the seed-vmapped TrainState (typed PRNG keys are stored as raw key data)."""

from __future__ import annotations

import dataclasses
import pathlib
from typing import Any

import jax
import numpy as np
import orbax.checkpoint as ocp

from jaxdeconf.errors import ConfigError
from jaxdeconf.sharding import place


def _to_raw(state: Any) -> dict[str, Any]:
    """The state's fields as a dict orbax can store: the typed key as uint32 data."""
    raw = {f.name: getattr(state, f.name) for f in dataclasses.fields(state)}
    raw["key"] = jax.random.key_data(state.key)
    return raw


def _from_raw(raw: dict[str, Any], like: Any) -> Any:
    """Inverse of ``_to_raw``, into the type of ``like``."""
    return type(like)(**{**raw, "key": jax.random.wrap_key_data(raw["key"])})


def _leading(metadata: Any) -> int:
    """The seed count of a checkpoint, from its metadata (every array's leading axis)."""
    tree = getattr(metadata, "tree", metadata)
    return int(jax.tree.leaves(tree, is_leaf=lambda x: hasattr(x, "shape"))[0].shape[0])


def _place_like(host: np.ndarray, like: jax.Array) -> jax.Array:
    """``host``'s first seeds (repeated cyclically where ``like`` has more) with the shape and placement of ``like``."""
    return place(host[np.arange(like.shape[0]) % host.shape[0]], like.sharding)


class Checkpoints:
    """Keeps the last two checkpoints of one algorithm's run under ``directory``, step = iterations done."""

    def __init__(self, directory: pathlib.Path) -> None:
        """Open (or create lazily) the checkpoint folder."""
        self.directory = pathlib.Path(directory).absolute()
        # A kill during a save leaves orbax's temporary folder behind (never a half checkpoint): delete it on start.
        options = ocp.CheckpointManagerOptions(max_to_keep=2, create=True, cleanup_tmp_directories=True)
        self.manager = ocp.CheckpointManager(self.directory, options=options,
                                             item_handlers=ocp.StandardCheckpointHandler())

    def latest_step(self) -> int | None:
        """Iterations done in the newest checkpoint, or None."""
        return self.manager.latest_step()

    def all_steps(self) -> list[int]:
        """Iterations done in every kept checkpoint."""
        return list(self.manager.all_steps())

    def save(self, step: int, state: Any) -> None:
        """Write a checkpoint (atomically: orbax renames a finished temporary folder)."""
        self.manager.save(step, args=ocp.args.StandardSave(_to_raw(state)))
        self.manager.wait_until_finished()

    def restore(self, step: int, like: Any) -> Any:
        """Read the checkpoint of ``step`` into the structure, seed count and placement of ``like``; a one-line
        ConfigError if unreadable.

        A checkpoint holds the seeds its run trained, padding seeds included (``jaxdeconf.sharding``), so it may hold
        more seeds than ``like`` (the first ones are read) or fewer (the padding seeds missing repeat saved ones:
        their results are dropped anyway). So a run resumes on another number of devices, and a trained policy loads
        on one device.
        """
        raw_like = _to_raw(like)
        try:
            saved = _leading(self.manager.item_metadata(step))
            target = jax.tree.map(lambda x: np.zeros((saved, *x.shape[1:]), x.dtype), raw_like)
            host = self.manager.restore(step, args=ocp.args.StandardRestore(target))
        except Exception as err:  # Orbax raises many types for damaged files; all mean the same to the user.
            reason = str(err).strip().splitlines()[0][:160] if str(err).strip() else type(err).__name__
            raise ConfigError(
                f"checkpoint {self.directory / str(step)} is unreadable ({reason}); it was left untouched: "
                "move it away to restart from the previous one, or pass --overwrite to retrain from scratch"
            ) from None
        return _from_raw(jax.tree.map(_place_like, host, raw_like), like)

    def close(self) -> None:
        """Release the manager's threads."""
        self.manager.close()
