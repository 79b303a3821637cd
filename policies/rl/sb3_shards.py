"""One SB3 ``VecEnv`` over several :class:`~policies.rl.vector_env.EgoVectorEnv` shards, each
in its own worker process: the batched ego env on every core.

An :class:`~policies.rl.vector_env.EgoVectorEnv` steps its N scenes in one process, on
one core (its adversary plans on one torch thread). :class:`ShardedEgoVecEnv` splits the
N scenes into ``shards`` contiguous groups and steps each group as an ``EgoVectorEnv``
in a worker process, all of them at once, the way SB3's ``SubprocVecEnv`` runs one
single env per process: scene ``i`` of the whole is the scene ``i`` of
:func:`~policies.rl.vector_env.build_vector_env` over all N (the same scenario draws and
the same adversary noise seed; its plans agree with the unsharded env's to float
rounding, as batched planning does with planning alone), and the same seed gives the
same rollout, bit for bit. ``env_method`` (e.g. the curriculum's
``set_adversary_stage``) reaches every shard.

    from policies.rl.sb3_shards import ShardedEgoVecEnv
    venv = VecMonitor(ShardedEgoVecEnv(config, num_envs=32, shards=2, seed=0))

A worker that fails raises a ``RuntimeError`` with its traceback in the main process
(the other workers are stopped) instead of leaving it waiting. Needs the ``rl`` extra.
"""

from __future__ import annotations

import multiprocessing
import signal
import traceback
from collections.abc import Callable, Sequence
from functools import partial
from multiprocessing.connection import Connection
from typing import Any

import numpy as np
from stable_baselines3.common.vec_env import VecEnv
from stable_baselines3.common.vec_env.base_vec_env import CloudpickleWrapper

from policies.rl.envs import EgoEnvConfig


def _build_shard(config: EgoEnvConfig, num_envs: int, seed: int) -> VecEnv:
    """A shard: the SB3 view of ``build_vector_env(config, num_envs, seed)``, one torch
    thread (one core per worker)."""
    import torch

    from policies.rl.sb3_vec_env import SB3EgoVecEnv
    from policies.rl.vector_env import build_vector_env

    torch.set_num_threads(1)
    return SB3EgoVecEnv(build_vector_env(config, num_envs, seed))


def _serve(remote: Connection, factory: CloudpickleWrapper) -> None:
    """A worker's loop: build the shard, answer ``(command, data)`` messages with
    ``("ok", result)`` or ``("error", traceback)``, until ``close``. Ignores SIGINT: on
    Ctrl-C the main process saves, then closes the workers."""
    signal.signal(signal.SIGINT, signal.SIG_IGN)
    venv: VecEnv | None = None
    while True:
        try:
            command, data = remote.recv()
        except (EOFError, KeyboardInterrupt):
            break
        try:
            if venv is None:
                venv = factory.var()
            if command == "spaces":
                result: Any = (venv.observation_space, venv.action_space)
            elif command == "reset":
                seed, options = data
                if seed is not None:
                    venv.seed(seed)
                if options:
                    venv.set_options(options)
                result = (venv.reset(), venv.reset_infos)
            elif command == "step":
                result = (*venv.step(data), venv.reset_infos)
            elif command == "get_attr":
                result = venv.get_attr(*data)
            elif command == "set_attr":
                result = venv.set_attr(*data)
            elif command == "env_method":
                name, args, kwargs, indices = data
                result = venv.env_method(name, *args, indices=indices, **kwargs)
            elif command == "close":
                venv.close()
                remote.send(("ok", None))
                break
            else:
                raise ValueError(f"unknown command {command!r}")
            remote.send(("ok", result))
        except AttributeError as error:
            if command != "get_attr":
                remote.send(("error", traceback.format_exc()))
            else:  # no such attribute: the caller's AttributeError, the worker lives on
                remote.send(("missing", str(error)))
        except Exception:  # noqa: BLE001  (sent to the main process, which raises it)
            remote.send(("error", traceback.format_exc()))
    remote.close()


class ShardedEgoVecEnv(VecEnv):
    """``num_envs`` training scenes of ``config`` in ``shards`` worker processes (module
    docstring).

    Args:
        config: the training env (as :func:`~policies.rl.vector_env.build_vector_env`).
        num_envs: scenes in all, >= ``shards``.
        shards: worker processes (>= 1); shard ``k`` steps scenes ``[start_k, stop_k)``,
            the groups as even as ``numpy.array_split`` makes them.
        seed: the adversaries' noise seed at construction (scene ``i``: ``seed + i``, as
            ``build_vector_env``; ``VecEnv.seed`` and ``reset`` re-seed as usual).
        start_method: multiprocessing start method (default ``"forkserver"`` where
            available, else ``"spawn"``; as SB3's ``SubprocVecEnv``).
    """

    def __init__(
        self,
        config: EgoEnvConfig,
        num_envs: int,
        shards: int = 2,
        seed: int = 0,
        start_method: str | None = None,
    ) -> None:
        if not isinstance(config, EgoEnvConfig):
            raise TypeError(f"config must be an EgoEnvConfig, got {type(config).__name__}")
        for name, value, low in (("shards", shards, 1), ("num_envs", num_envs, shards)):
            if isinstance(value, bool) or not isinstance(value, (int, np.integer)) or value < low:
                raise ValueError(f"{name} must be an int >= {low}, got {value!r}")
        groups = np.array_split(np.arange(int(num_envs)), int(shards))
        self.starts = [int(group[0]) for group in groups]
        self.stops = [int(group[-1]) + 1 for group in groups]
        if start_method is None:
            methods = multiprocessing.get_all_start_methods()
            start_method = "forkserver" if "forkserver" in methods else "spawn"
        context = multiprocessing.get_context(start_method)
        self.remotes: list[Connection] = []
        self.processes = []
        for start, stop in zip(self.starts, self.stops, strict=True):
            remote, work_remote = context.Pipe()
            factory = CloudpickleWrapper(partial(_build_shard, config, stop - start, seed + start))
            process = context.Process(target=_serve, args=(work_remote, factory), daemon=True)
            process.start()
            work_remote.close()
            self.remotes.append(remote)
            self.processes.append(process)
        self.closed = False
        observation_space, action_space = self._ask([("spaces", None)] * len(self.remotes))[0]
        super().__init__(int(num_envs), observation_space, action_space)

    # ------------------------------------------------------------------ VecEnv
    def reset(self) -> np.ndarray:
        """Reset every scene, with the seeds of the last ``seed(...)`` if any."""
        seeds = [self._seeds[start] for start in self.starts]  # shard k: seed + start_k + j
        options = self._options[0] or None
        answers = self._ask([("reset", (seed, options)) for seed in seeds])
        self.reset_infos = [info for _, infos in answers for info in infos]
        self._reset_seeds()
        self._reset_options()
        return np.concatenate([observations for observations, _ in answers])

    def step_async(self, actions: np.ndarray) -> None:
        actions = np.asarray(actions)
        if len(actions) != self.num_envs:
            raise ValueError(
                f"actions must have num_envs = {self.num_envs} rows, got {len(actions)}"
            )
        self._send(
            [
                ("step", actions[start:stop])
                for start, stop in zip(self.starts, self.stops, strict=True)
            ]
        )
        self.waiting = True

    def step_wait(self) -> tuple[np.ndarray, np.ndarray, np.ndarray, list[dict[str, Any]]]:
        if not getattr(self, "waiting", False):
            raise RuntimeError("step_wait() called without step_async(actions)")
        self.waiting = False
        answers = self._receive()
        self.reset_infos = [info for *_, infos in answers for info in infos]
        observations, rewards, dones, infos = (
            np.concatenate([answer[0] for answer in answers]),
            np.concatenate([answer[1] for answer in answers]),
            np.concatenate([answer[2] for answer in answers]),
            [info for answer in answers for info in answer[3]],
        )
        return observations, rewards, dones, infos

    def close(self) -> None:
        """Stop the workers (their envs closed first when they still answer)."""
        if self.closed:
            return
        self.closed = True
        for remote, process in zip(self.remotes, self.processes, strict=True):
            try:
                if process.is_alive():
                    remote.send(("close", None))
                    remote.recv()
            except (BrokenPipeError, EOFError, OSError):
                pass
            process.join(timeout=10)
            if process.is_alive():
                process.terminate()
            remote.close()

    def get_attr(self, attr_name: str, indices: Any = None) -> list[Any]:
        """The attribute of each requested scene's vector env (one per scene)."""
        return self._per_scene("get_attr", lambda local: (attr_name, local), indices)

    def set_attr(self, attr_name: str, value: Any, indices: Any = None) -> None:
        """Set an attribute of the shards' vector envs (all scenes only, as the unsharded
        env: its scenes share one vector env)."""
        if len(list(self._get_indices(indices))) != self.num_envs:
            raise ValueError("set_attr: each shard's scenes share one vector env; set it for all")
        self._per_scene("set_attr", lambda local: (attr_name, value, local), None)

    def env_method(
        self, method_name: str, *method_args: Any, indices: Any = None, **method_kwargs: Any
    ) -> list[Any]:
        """Call a method of each shard holding a requested scene (e.g.
        ``set_adversary_stage``); its result per requested scene."""
        return self._per_scene(
            "env_method", lambda local: (method_name, method_args, method_kwargs, local), indices
        )

    def env_is_wrapped(self, wrapper_class: type, indices: Any = None) -> list[bool]:
        return [False for _ in self._get_indices(indices)]

    # ------------------------------------------------------------ internals
    def _per_scene(self, command: str, payload: Callable[[list[int]], Any], indices: Any) -> list:
        """Send ``command`` to each shard holding one of ``indices`` (its local indices in
        the payload); the answers, one per requested scene, in the order asked."""
        wanted = list(self._get_indices(indices))
        shards, messages, held = [], [], []
        for shard, (start, stop) in enumerate(zip(self.starts, self.stops, strict=True)):
            mine = [index for index in wanted if start <= index < stop]
            if mine:
                shards.append(shard)
                messages.append((command, payload([index - start for index in mine])))
                held.append(mine)
        answers = self._ask(messages, shards)
        if command == "set_attr":
            return []
        values = {}
        for mine, answer in zip(held, answers, strict=True):
            values.update(zip(mine, answer, strict=True))
        return [values[index] for index in wanted]

    def _send(
        self, messages: Sequence[tuple[str, Any]], shards: Sequence[int] | None = None
    ) -> None:
        """Send ``messages[j]`` to shard ``shards[j]`` (default: one to each shard)."""
        if self.closed:
            raise RuntimeError("the sharded env is closed")
        self._pending = list(range(len(self.remotes)) if shards is None else shards)
        for shard, message in zip(self._pending, messages, strict=True):
            try:
                self.remotes[shard].send(message)
            except OSError as error:  # BrokenPipeError: the process is gone
                self._fail([(shard, f"the worker process died ({error!r})")])

    def _receive(self) -> list[Any]:
        """The answers of the shards last sent to, in order; RuntimeError if any failed,
        AttributeError if ``get_attr`` asked for an attribute that is not there."""
        answers, errors, missing = [], [], []
        for shard in self._pending:
            try:
                status, value = self.remotes[shard].recv()
            except (EOFError, OSError) as error:  # the process died (e.g. killed)
                status, value = "error", f"the worker process died without an answer ({error!r})"
            if status == "error":
                errors.append((shard, value))
            elif status == "missing":
                missing.append(value)
            answers.append(value)
        if errors:
            self._fail(errors)
        if missing:
            raise AttributeError(missing[0])
        return answers

    def _fail(self, errors: list[tuple[int, str]]) -> None:
        """Close every worker and raise a RuntimeError naming the failed shards."""
        self.close()
        detail = "\n".join(
            f"shard {shard} (scenes {self.starts[shard]}..{self.stops[shard] - 1}): {text}"
            for shard, text in errors
        )
        raise RuntimeError(f"a ShardedEgoVecEnv worker failed; {detail}")

    def _ask(
        self, messages: Sequence[tuple[str, Any]], shards: Sequence[int] | None = None
    ) -> list[Any]:
        self._send(messages, shards)
        return self._receive()


__all__: Sequence[str] = ["ShardedEgoVecEnv"]
