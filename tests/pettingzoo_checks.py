"""PettingZoo's checks of a parallel env, as the env, wrapper and adversary tests run them."""

from __future__ import annotations

from collections.abc import Callable

from pettingzoo import ParallelEnv
from pettingzoo.test import parallel_api_test, parallel_seed_test


def pettingzoo_checks(make_env: Callable[[], ParallelEnv], num_cycles: int = 30) -> None:
    """PettingZoo's API test on one env from ``make_env``, then its seed test (two envs
    from ``make_env``, reset with one seed, must give the same episode)."""
    parallel_api_test(make_env(), num_cycles=num_cycles)
    parallel_seed_test(make_env, num_cycles=num_cycles)
