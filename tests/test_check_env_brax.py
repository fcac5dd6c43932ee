"""check_env on the Brax envs, at a short horizon (the compile, not the horizon, is what costs: about 35 s for
half_cheetah and 25 s for ant_goal on one core; the cheetah's is in the slow tier). Its own file, so pytest-xdist runs
it beside the others."""

from __future__ import annotations

import pytest
from jaxdeconf.envs import check_env, make


@pytest.mark.timeout(900)
# The cheetah shares the Brax wrapper with the ant; its dynamics are checked in test_locomotion.py.
@pytest.mark.parametrize("name", [pytest.param("half_cheetah", marks=pytest.mark.slow), "ant_goal"])
def test_check_env_passes_on_brax_envs(name):
    env, params = make(name, horizon=4)
    check_env(env, params, samples=16)
