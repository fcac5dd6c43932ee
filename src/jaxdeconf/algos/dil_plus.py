"""``dil_plus``: the deconfounded imitator of ``dil`` (Algorithm 1 at training time, Algorithm 2 at test time) with
this project's changes to how its networks read their inputs, one configuration on every environment.

Only the defaults of its section differ from ``dil``'s; presets set neither (they differ by env in sizes and budgets
alone). docs/algorithms.md has the table of the changes, each with what it measured.
"""

from __future__ import annotations

import dataclasses

from jaxdeconf.algos.dil import (
    ENCODERS,
    FUSIONS,
    POLICY_LATENTS,
    Deconfounded,
    DilConfig,
)
from jaxdeconf.config import field


@dataclasses.dataclass(frozen=True)
class DilPlusConfig(DilConfig):
    """``DilConfig``'s fields with this method's defaults (``--set dil_plus.<field>=...`` to ablate one); the decoder's
    weighting and likelihoods are ``dil``'s."""

    # q_phi reads each whole transition, where the evidence about θ is (on LunarLander the paper's input ends below
    # naive BC).
    encoder_deltas: bool = True
    # A product of per-step Gaussian factors: once the evidence is in, the belief cannot fade (the GRU's does, e.g.
    # when the ant stands at its goal and its steps stop telling where the goal is).
    encoder: str = field("evidence", ENCODERS)
    # The policy is cloned on the codes q_phi writes on the imitator's own episodes, where it reads θ-hat online
    # (64 evenly spaced slots of the own buffer bound the matching's cost).
    policy_latent: str = field("matched", POLICY_LATENTS)
    match_codes: int = field(64, ">=0")
    # θ-hat beside the observation at the policy's input, where the oracle's θ sits in its view.
    policy_fusion: str = field("early", FUSIONS)


@dataclasses.dataclass(frozen=True)
class DeconfoundedPlus(Deconfounded):
    """``dil`` with ``DilPlusConfig``'s way of reading its inputs."""

    settings = ("dil_plus", DilPlusConfig)
    method_section = "dil_plus"
