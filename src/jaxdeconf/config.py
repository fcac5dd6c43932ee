"""One frozen config tree per run: the shared sections (``model``, ``train``), each algorithm's own section, dotted
overrides from the command line and validation.

The sections an algorithm owns (``dagger``, ``gail``, ``offline``) are declared in its own file and reach a Config
through ``jaxdeconf.resolve``, which knows the registry; this module knows no algorithm.
"""

from __future__ import annotations

import dataclasses
import json
import math
from collections.abc import Mapping
from typing import Any

from jaxdeconf.envs import parse_bool
from jaxdeconf.errors import ConfigError

CELLS = ("gru", "mingru")

#: Every integer field passes through int32 inside the compiled programs (shapes, counters, seeds).
INT32_MAX = 2**31 - 1


def field(default: Any, allowed: str | tuple[str, ...]) -> Any:
    """A config field with its allowed values stated once, next to it: ``">0"``, ``">=1"`` or a tuple of choices.

    ``validate`` checks every field of every section against this (and rejects NaN and infinities everywhere).
    """
    return dataclasses.field(default=default, metadata={"allowed": allowed})


@dataclasses.dataclass(frozen=True)
class ModelConfig:
    """Network sizes (static: they fix shapes) and the recurrent cell. How the deconfounded algorithms' networks read
    their inputs is each one's own section (``dil``, ``dil_plus``)."""

    width: int = field(128, ">=1")  # Hidden width of every MLP block (Linear -> LayerNorm -> ELU, two blocks).
    action_embed: int = field(32, ">=1")  # Size of the previous-action embedding fed to the GRUs.
    gru: int = field(500, ">=1")  # GRU hidden size of the inference model q_phi.
    bc_gru: int = field(500, ">=1")  # GRU hidden size of the recurrent naive-BC / oracle / DAgger policy.
    latent: int = field(64, ">=1")  # Latent size of theta-hat.
    cell: str = field("gru", CELLS)  # Cell of the GRU q_phi and the recurrent policies: "gru" (paper's), "mingru".


@dataclasses.dataclass(frozen=True)
class TrainConfig:
    """Loop counts (static) and optimisation constants."""

    iterations: int = field(300, ">=1")  # Outer iterations (Algorithm 1's while-loop).
    # First iterations that collect data (and train the encoder) but do not update the policy.
    warmup: int = field(20, ">=0")
    # Iterations per compiled chunk; progress, metrics and checkpoints happen once per chunk.
    chunk: int = field(10, ">=1")
    episodes_per_iter: int = field(16, ">=1")  # Episodes collected per data stream per iteration.
    batch_size: int = field(16, ">=1")  # Whole episodes per gradient step.
    policy_steps: int = field(100, ">=1")  # Policy (BC) gradient steps per iteration.
    encoder_steps: int = field(100, ">=1")  # Inference-model (ELBO) gradient steps per iteration (dil only).
    buffer_episodes: int = field(2000, ">=1")  # Replay-buffer capacity per data stream, in whole episodes.
    policy_lr: float = field(3e-4, ">0")  # AdamW learning rate of the policy.
    encoder_lr: float = field(3e-4, ">0")  # AdamW learning rate of encoder and decoder.
    weight_decay: float = field(0.01, ">=0")  # AdamW weight decay.
    encoder_clip: float = field(100.0, ">0")  # Global-norm gradient clip of the inference model.
    policy_clip: float = field(100.0, ">0")  # Global-norm gradient clip of the policy.
    beta: float = field(1.0, ">=0")  # KL weight of the sequential ELBO (eq. 11).
    prediction_steps: int = field(1, ">=1")  # K: how many future observations the decoder predicts from z_t.
    eval_episodes: int = field(64, ">=1")  # Online evaluation episodes per chunk.
    # Seeds a device computes at once (vmapped); the rest of its seeds follow in turn. 0 (the default) vmaps all of a
    # device's seeds, faster than one at a time also on a CPU (docs/scale.md); 1 makes every seed's run the same
    # program whatever the number of seeds, so a seed's results are identical to the bit alone or among others.
    seed_batch: int = field(0, ">=0")


@dataclasses.dataclass(frozen=True)
class Config:
    """A whole experiment: environment, algorithms, seeds, the shared sections and each algorithm's own section.

    ``settings`` maps a section name (``"gail"``) to the dataclass an algorithm declares for it; ``config.gail`` reads
    it like the shared sections.
    """

    env: str = "bandit"
    env_params: dict[str, Any] = dataclasses.field(default_factory=dict)  # Overrides of the env's defaults.
    algos: tuple[str, ...] = ("bc", "dil")
    seeds: int = field(10, ">=1")  # Number of seeds, trained together in one vmapped program.
    seed_start: int = field(0, ">=0")  # Seeds are seed_start .. seed_start + seeds - 1.
    model: ModelConfig = ModelConfig()
    train: TrainConfig = TrainConfig()
    settings: Mapping[str, Any] = dataclasses.field(default_factory=dict)  # Algorithm-owned sections, by name.

    def __getattr__(self, name: str) -> Any:
        """An algorithm-owned section by name (``config.gail``)."""
        settings = self.__dict__.get("settings", {})
        if name in settings:
            return settings[name]
        raise AttributeError(f"{type(self).__name__} has no section {name!r}; sections: {', '.join(self.sections)}")

    @property
    def sections(self) -> tuple[str, ...]:
        """Every section's name, each overridable as ``section.field`` from the command line."""
        return ("model", "train", *self.settings)

    @property
    def num_chunks(self) -> int:
        """Number of compiled chunks (the last may hold fewer iterations)."""
        return -(-self.train.iterations // self.train.chunk)

    def to_dict(self) -> dict[str, Any]:
        """JSON-ready nested dict: the algorithm-owned sections sit beside ``model`` and ``train``."""
        out = {f.name: getattr(self, f.name) for f in dataclasses.fields(self) if f.name != "settings"}
        out = {**out, "model": dataclasses.asdict(self.model), "train": dataclasses.asdict(self.train)}
        out["env_params"], out["algos"] = dict(self.env_params), list(self.algos)
        return {**out, **{name: dataclasses.asdict(s) for name, s in self.settings.items()}}


def _coerce(value: Any, default: Any, name: str) -> Any:
    """Convert a command-line string to the type of the field's default."""
    if isinstance(default, bool):
        try:
            return parse_bool(value)
        except ValueError:
            raise ConfigError(f"{name}={value!r} is not a boolean (allowed: true, false)") from None
    try:
        return type(default)(value)
    except (TypeError, ValueError):
        raise ConfigError(f"{name}={value!r} is not a valid {type(default).__name__}") from None


def apply_overrides(config: Config, overrides: dict[str, Any]) -> Config:
    """Return ``config`` with dotted overrides (``train.iterations``, ``model.gru``, ``gail.lr``, ``env.p``)."""
    sections: dict[str, dict[str, Any]] = {name: {} for name in config.sections}
    env_params = dict(config.env_params)
    top: dict[str, Any] = {}
    for name, value in overrides.items():
        section, _, key = name.partition(".")
        if section == "env" and key:
            env_params[key] = value
        elif section in sections and key:
            sub = getattr(config, section)
            names = {f.name for f in dataclasses.fields(sub)}
            if key not in names:
                raise ConfigError(f"unknown field {name!r}; allowed {section}.* fields: {', '.join(sorted(names))}")
            sections[section][key] = _coerce(value, getattr(sub, key), name)
        elif name in ("seeds", "seed_start"):
            top[name] = _coerce(value, getattr(config, name), name)
        else:
            allowed = ", ".join(f"{s}.*" for s in ("env", *config.sections))
            raise ConfigError(f"unknown field {name!r}; allowed: {allowed}, seeds, seed_start")
    replaced = {name: dataclasses.replace(getattr(config, name), **fields) for name, fields in sections.items()}
    settings = {name: replaced.pop(name) for name in config.settings}
    return dataclasses.replace(config, env_params=env_params, settings=settings, **replaced, **top)


def _need(kind: str, rule: str) -> str:
    """What a range rule asks for, in words: ``need a positive integer``, ``need a number > 0``."""
    if (kind, rule) == ("int", ">=1"):
        return "need a positive integer"
    op = rule.rstrip("0123456789.")
    return f"need {'an integer' if kind == 'int' else 'a number'} {op} {rule[len(op):]}"


def _check_field(name: str, value: Any, default: Any, allowed: Any) -> None:
    """Raise ConfigError if one field's value has the wrong type, is not finite, or breaks its stated range."""
    kind = type(default)
    if kind is float and type(value) is int:
        value = float(value)  # JSON writes 1.0 as 1.0, but a hand-edited 1 is still a fine float.
    if type(value) is not kind:
        raise ConfigError(f"{name}={value!r} is not a valid {kind.__name__}")
    if kind is float and not math.isfinite(value):
        raise ConfigError(f"{name}={value} is not allowed: need a finite number")
    if isinstance(allowed, tuple) and value not in allowed:
        raise ConfigError(f"{name}={value!r} is not allowed; allowed: {', '.join(allowed)}")
    if isinstance(allowed, str):
        op, bound = allowed.rstrip("0123456789."), float(allowed.lstrip("<>="))
        ok = {">": value > bound, ">=": value >= bound}[op]
        if not ok:
            raise ConfigError(f"{name}={value} is not allowed: {_need(kind.__name__, allowed)}")
    if kind is int and value > INT32_MAX:
        raise ConfigError(f"{name}={value} is too large: need at most {INT32_MAX}")


def _fields(section: Any, prefix: str = "") -> list[tuple[str, Any, Any, Any]]:
    """(dotted name, value, default, allowed or None) of every scalar field, walking nested dataclass sections: a
    field without a stated range is still checked for its type, finiteness and the int32 bound."""
    out = []
    for f in dataclasses.fields(section):
        value = getattr(section, f.name)
        if dataclasses.is_dataclass(value):
            out += _fields(value, f"{prefix}{f.name}.")
        elif type(f.default) in (int, float, str, bool):
            out.append((f"{prefix}{f.name}", value, f.default, f.metadata.get("allowed")))
    for name, sub in getattr(section, "settings", {}).items():
        out += _fields(sub, f"{prefix}{name}.")
    return out


def validate(config: Config) -> None:
    """Raise ConfigError naming the first value outside its allowed range (the algorithm names are
    ``jaxdeconf.resolve``'s to check: this module knows no registry)."""
    for name, value, default, allowed in _fields(config):
        _check_field(name, value, default, allowed)
    # Relations between fields.
    t = config.train
    if t.warmup >= t.iterations:
        raise ConfigError(f"train.warmup={t.warmup} is not allowed: need 0 <= warmup < train.iterations")
    if t.chunk > t.iterations:
        raise ConfigError(f"train.chunk={t.chunk} is not allowed: need at most train.iterations={t.iterations} "
                          "(progress, metrics and checkpoints come once per chunk)")
    if t.batch_size > t.buffer_episodes:
        raise ConfigError(f"train.batch_size={t.batch_size} exceeds train.buffer_episodes={t.buffer_episodes}: "
                          "a batch must fit in the buffer")
    if config.seed_start + config.seeds - 1 > INT32_MAX:
        raise ConfigError(f"seed_start={config.seed_start} is too large: seeds seed_start .. seed_start + seeds - 1 "
                          f"must be at most {INT32_MAX}")
    for settings in config.settings.values():
        check = getattr(settings, "check", None)
        if check is not None:
            check(config)  # An algorithm's relations between its own fields and the shared ones.


def from_dict(data: dict[str, Any], settings: Mapping[str, type]) -> Config:
    """Inverse of ``Config.to_dict`` given the algorithm-owned section classes by name; a section or field missing
    from ``data`` takes its default."""
    return Config(
        env=data["env"],
        env_params=dict(data["env_params"]),
        algos=tuple(data["algos"]),
        seeds=int(data["seeds"]),
        seed_start=int(data.get("seed_start", 0)),
        model=_section(ModelConfig, "model", data["model"]),
        train=_section(TrainConfig, "train", data["train"]),
        settings={name: _section(cls, name, data.get(name, {})) for name, cls in settings.items()},
    )


def _section(cls: type, name: str, fields: dict[str, Any]) -> Any:
    """Section ``cls`` from saved ``fields``; ConfigError naming a field this version does not have."""
    known = {f.name for f in dataclasses.fields(cls)}
    unknown = sorted(set(fields) - known)
    if unknown:
        raise ConfigError(f"{name}.{unknown[0]} is not a setting of this version; allowed {name}.* fields: "
                          f"{', '.join(sorted(known))}")
    return cls(**fields)


def dumps(config: Config) -> str:
    """Canonical JSON text of a config (used to compare a results folder's config with a new one)."""
    return json.dumps(config.to_dict(), indent=2, sort_keys=True)
