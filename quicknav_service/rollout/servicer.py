"""The gRPC ``Rollout`` servicer: one bidirectional stream per agent, one batch of envs per stream.

Protocol (quicknav/v1/rollout.proto): Start -> Started, Step -> Transition, Reset -> ResetDone,
Close -> Closed. Every refused request ends the stream with an exact status code and a message
naming what was wrong and what is allowed; nothing a client sends can take down the server or
another stream. JAX calls run on a thread pool, never on the event loop.
"""

from __future__ import annotations

import asyncio
import logging
import uuid
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import grpc
import numpy as np
from quicknav_client.proto.quicknav.v1 import rollout_pb2 as pb
from quicknav_client.proto.quicknav.v1 import rollout_pb2_grpc as pb_grpc
from quicknav_client.tensors import TensorError, decode, encode

from quicknav_core.runtime import Runtime
from quicknav_service import auth
from quicknav_service.rollout.common import (
    Refused,
    StreamMemory,
    authenticate,
    bounded,
    is_plain_id,
    read_next,
    run_copy,
)
from quicknav_service.rollout.start import StartRequest, admit_start, read_start, start_loc
from quicknav_service.settings import Settings

log = logging.getLogger("quicknav.rollout")

# Stepping this few envs costs less than the hop to a worker thread; they run inline.
INLINE_MAX_ENVS = 64


@dataclass
class Session:
    id: str = field(default_factory=lambda: uuid.uuid4().hex[:12])
    env: Any = None  # quicknav_core.env.batch.BatchedEnv once started (lock-step)
    groups: list = field(default_factory=list)  # asynchronous mode: one BatchedEnv per group
    counted: bool = False  # holds one of the server's session slots
    steps: int = 0  # Step messages served
    env_steps: int = 0
    episodes: int = 0
    group_steps: list[int] = field(default_factory=list)
    in_flight: dict[int, asyncio.Task] = field(default_factory=dict)  # group -> its step
    write_lock: asyncio.Lock = field(default_factory=asyncio.Lock)

    @property
    def started(self) -> bool:
        return self.env is not None or bool(self.groups)

    async def settle(self) -> None:
        """Wait for the groups' steps in flight (their Transitions are written first)."""
        if self.in_flight:
            await asyncio.gather(*self.in_flight.values(), return_exceptions=True)


def group_seed(seed: int, group: int) -> int:
    """The seed of group ``group`` of a stream started with ``seed`` (asynchronous mode)."""
    return int(np.random.SeedSequence([seed, group]).generate_state(1)[0])


def _transition(r, step_count: int, group: int = 0) -> pb.ServerMessage:
    return pb.ServerMessage(
        transition=pb.Transition(
            observations=encode(r.obs),
            rewards=encode(r.reward),
            terminated=encode(r.terminated),
            truncated=encode(r.truncated),
            done_indices=encode(r.done_indices),
            final_observations=encode(r.final_obs),
            collisions=encode(r.collision),
            step_count=step_count,
            group=group,
        )
    )


def _box(low: np.ndarray, high: np.ndarray) -> pb.BoxSpec:
    return pb.BoxSpec(dtype="float32", shape=list(low.shape), low=encode(low), high=encode(high))


class RolloutServicer(pb_grpc.RolloutServiceServicer):
    """Serves ``RolloutService.Rollout``; one instance per server, any number of streams."""

    def __init__(self, settings: Settings, executor: ThreadPoolExecutor | None = None,
                 runtime: Runtime | None = None, auth_limiter: auth.Limiter | None = None):  # fmt: skip
        from quicknav_service.runtime import service_runtime

        self.settings = settings
        # room banks (kept on the data disk), uploaded maps, compiled steppers: one per process
        self.runtime = runtime if runtime is not None else service_runtime(settings)
        self.executor = executor or ThreadPoolExecutor(
            max_workers=min(32, settings.rollout_max_sessions + 2), thread_name_prefix="rollout"
        )
        self.active_sessions = 0
        # what the open streams hold together, by their estimates (one server, one budget)
        budget = settings.rollout_memory_mb or settings.max_job_memory_mb
        setting = ("QUICKNAV_ROLLOUT_MEMORY_MB" if settings.rollout_memory_mb
                   else "QUICKNAV_MAX_JOB_MEMORY_MB, as QUICKNAV_ROLLOUT_MEMORY_MB is unset")  # fmt: skip
        self.memory = StreamMemory(budget, setting)
        self.auth_limiter = auth_limiter if auth_limiter is not None else auth.make_limiter(settings)
        self.env_steps_served = 0  # env steps (steps x envs) over every stream, for /metrics
        self._handlers = {
            "start": self._start,
            "step": self._step,
            "reset": self._reset,
            "close": self._close,
        }

    async def _run(self, fn, *args):
        return await asyncio.get_running_loop().run_in_executor(self.executor, fn, *args)

    # ------------------------------------------------------------------ the stream
    async def Rollout(self, request_iterator, context: grpc.aio.ServicerContext):
        await authenticate(self.settings, self.auth_limiter, context)
        session = Session()
        idle = self.settings.rollout_idle_s
        try:
            while True:
                msg = await read_next(context, idle, "quicknav.v1.AgentMessage",
                                      "the session was closed; open a new stream and send Start")  # fmt: skip
                if msg is grpc.aio.EOF:
                    return
                kind = msg.WhichOneof("payload")
                handler = self._handlers.get(kind)
                if handler is None:
                    raise Refused(
                        grpc.StatusCode.INVALID_ARGUMENT,
                        "empty AgentMessage: set one of start, step, reset, close",
                    )
                finished = await handler(session, getattr(msg, kind), context)
                if finished:
                    return
        except Refused as r:
            await context.abort(r.code, bounded(r.message))
        except asyncio.CancelledError:
            raise  # the client went away
        except Exception as e:  # a bug, not a bad request: say so, keep serving others
            log.exception("rollout session %s failed", session.id)
            await context.abort(grpc.StatusCode.INTERNAL, bounded(f"{type(e).__name__}: {e}"))
        finally:
            for task in session.in_flight.values():
                task.cancel()
            if session.counted:
                self.active_sessions -= 1
                self.memory.give_back(session.id)

    # ------------------------------------------------------------------ handlers
    async def _start(self, session: Session, start: pb.Start, context) -> bool:
        if session.started:
            raise Refused(
                grpc.StatusCode.FAILED_PRECONDITION,
                "Start was already sent on this stream: send Reset for new episodes, or open a"
                " new stream for another config",
            )
        s = self.settings
        policy_run = None
        if start.HasField("policy") and start.policy.job_id:
            # a trained job's episodes: the Start's fields apply to the env it was trained in
            policy_run = await asyncio.to_thread(self._policy_run, start.policy.job_id)
        req = read_start(start, policy_run[1] if policy_run else None)
        # every door's admission (limits, rooms, memory): off the event loop, it may read maps
        await self._run(admit_start, req, s, self.runtime)
        if self.active_sessions >= s.rollout_max_sessions:
            raise Refused(
                grpc.StatusCode.RESOURCE_EXHAUSTED,
                f"{self.active_sessions} rollout sessions are open, the limit"
                f" (QUICKNAV_ROLLOUT_MAX_SESSIONS) is {s.rollout_max_sessions}: close one or retry"
                " later",
            )
        from quicknav_core.admission import stream_estimate

        estimate, field = stream_estimate(req.rollout)  # (policy mode: an evaluation's)
        self.memory.take(session.id, estimate, ".".join(start_loc(field)))
        self.active_sessions += 1
        session.counted = True
        if policy_run:
            await self._stream_policy(session, req, policy_run[0], context)
            return True
        from quicknav_core.env.clearance import RobotFitError

        try:
            session.env, session.groups, obs = await self._run(self._build, req)
        except RobotFitError as e:
            # a room past those admission checked that the robot fits in (the door checks the
            # first rooms of each bank, the env build every room): the Start's mistake
            raise Refused(grpc.StatusCode.INVALID_ARGUMENT, f"start.config.{e}") from None
        session.group_steps = [0] * len(session.groups)
        from quicknav_core.env.constants import observation_bounds

        low, high = observation_bounds(req.env)
        await context.write(
            pb.ServerMessage(
                started=pb.Started(
                    session_id=session.id,
                    num_envs=req.num_envs,
                    observation_space=_box(low, high),
                    action_space=_box(-np.ones(2, np.float32), np.ones(2, np.float32)),
                    observations=encode(obs),
                    env_config_json=req.env.model_dump_json(),
                    max_steps=req.env.max_steps,
                    groups=req.groups,
                )
            )
        )
        return False

    def _build(self, req: StartRequest):
        """The stream's envs (one batch, or a batch per group) and their first observations."""
        from quicknav_core.env.batch import BatchedEnv

        if req.groups == 1:
            env = BatchedEnv(req.env, req.num_envs, seed=req.seed % 2**32, split=req.split,
                             runtime=self.runtime)  # fmt: skip
            return env, [], env.reset()
        k = req.num_envs // req.groups
        envs = [BatchedEnv(req.env, k, seed=group_seed(req.seed, g), split=req.split,
                           runtime=self.runtime) for g in range(req.groups)]  # fmt: skip
        return None, envs, np.concatenate([e.reset() for e in envs])

    def _actions(self, n: int, step: pb.Step) -> np.ndarray:
        if not step.HasField("actions"):
            raise Refused(grpc.StatusCode.INVALID_ARGUMENT, f"step.actions is missing: send a"
                          f" float32 tensor of shape [{n}, 2]")  # fmt: skip
        try:
            actions = decode(step.actions, "step.actions")
        except TensorError as e:
            raise Refused(grpc.StatusCode.INVALID_ARGUMENT, str(e)) from None
        if actions.dtype.kind != "f":
            raise Refused(
                grpc.StatusCode.INVALID_ARGUMENT,
                f"step.actions.dtype={actions.dtype.name}: allowed float32 (or float16/float64)",
            )
        if actions.shape != (n, 2):
            raise Refused(
                grpc.StatusCode.INVALID_ARGUMENT,
                f"step.actions has shape {list(actions.shape)}; expected [{n}, 2] (the envs of"
                " this session or group, then left and right wheel speed in [-1, 1])",
            )
        bad = ~np.isfinite(actions)
        if bad.any():
            envs = np.flatnonzero(bad.any(axis=1))
            raise Refused(
                grpc.StatusCode.INVALID_ARGUMENT,
                f"step.actions holds NaN or infinite values for env(s) {envs[:8].tolist()}"
                f"{' …' if envs.size > 8 else ''}; actions must be finite, in [-1, 1]",
            )
        return actions

    async def _step(self, session: Session, step: pb.Step, context) -> bool:
        if not session.started:
            raise Refused(
                grpc.StatusCode.FAILED_PRECONDITION, "Step before Start: send Start first"
            )
        if session.groups:
            return await self._step_async(session, step, context)
        if step.group:
            raise Refused(grpc.StatusCode.INVALID_ARGUMENT,
                          f"step.group={step.group} in a lock-step session: send 0 (groups are"
                          " set by start.groups)")  # fmt: skip
        env = session.env
        actions = self._actions(env.num_envs, step)
        if env.num_envs <= INLINE_MAX_ENVS:
            r = env.step(actions)
        else:
            r = await self._run(env.step, actions)
        self._count(session, r, env.num_envs)
        await context.write(_transition(r, session.steps))
        return False

    def _count(self, session: Session, r, n: int) -> None:
        session.steps += 1
        session.env_steps += n
        self.env_steps_served += n
        session.episodes += int(r.done_indices.size)

    async def _step_async(self, session: Session, step: pb.Step, context) -> bool:
        g = step.group
        if g >= len(session.groups):
            raise Refused(grpc.StatusCode.INVALID_ARGUMENT,
                          f"step.group={g}: allowed range 0..{len(session.groups) - 1}")  # fmt: skip
        if g in session.in_flight:
            raise Refused(grpc.StatusCode.FAILED_PRECONDITION,
                          f"step.group={g} has a Step in flight: wait for its Transition")  # fmt: skip
        env = session.groups[g]
        actions = self._actions(env.num_envs, step)
        session.in_flight[g] = asyncio.create_task(self._step_group(session, g, env, actions, context))
        return False

    async def _step_group(self, session: Session, g: int, env, actions, context) -> None:
        """Step one group and send its Transition; the stream reads on meanwhile."""
        try:
            r = await self._run(env.step, actions)
            self._count(session, r, env.num_envs)
            session.group_steps[g] += 1
            message = _transition(r, session.group_steps[g], g)
            # the group is free before its Transition leaves: the agent's next Step for it may
            # arrive as soon as the Transition does
            session.in_flight.pop(g, None)
            async with session.write_lock:
                await context.write(message)
        except asyncio.CancelledError:
            raise
        except Exception as e:  # a bug, not a bad request: end the stream and say so
            log.exception("rollout session %s, group %d failed", session.id, g)
            await context.abort(grpc.StatusCode.INTERNAL, bounded(f"{type(e).__name__}: {e}"))
        finally:
            session.in_flight.pop(g, None)

    async def _reset(self, session: Session, reset: pb.Reset, context) -> bool:
        if not session.started:
            raise Refused(
                grpc.StatusCode.FAILED_PRECONDITION, "Reset before Start: send Start first"
            )
        await session.settle()
        if session.groups:
            base = reset.seed if reset.HasField("seed") else None

            def reset_all():
                return np.concatenate([
                    e.reset(None if base is None else group_seed(base, g))
                    for g, e in enumerate(session.groups)])  # fmt: skip

            obs = await self._run(reset_all)
        else:
            seed = reset.seed % 2**32 if reset.HasField("seed") else None
            obs = await self._run(session.env.reset, seed)
        async with session.write_lock:
            await context.write(pb.ServerMessage(reset=pb.ResetDone(observations=encode(obs))))
        return False

    async def _close(self, session: Session, close: pb.Close, context) -> bool:
        await session.settle()
        async with session.write_lock:
            await context.write(
                pb.ServerMessage(
                    closed=pb.Closed(
                        steps=session.steps, env_steps=session.env_steps, episodes=session.episodes
                    )
                )
            )
        return True

    # ------------------------------------------------------------------ policy mode
    def _policy_run(self, job_id: str):
        """(run folder, the env it trained in) of a train job with a checkpoint, or NOT_FOUND."""
        from quicknav_core.train.run import read_config

        run_dir = run_copy(self.runtime, job_id, "start.policy.job_id") if is_plain_id(job_id) else None
        if run_dir is None:
            raise Refused(
                grpc.StatusCode.NOT_FOUND,
                f"start.policy.job_id={job_id!r}: no train job with a checkpoint by that id in"
                " this service's artifacts",
            )
        return run_dir, read_config(run_dir).env

    async def _stream_policy(self, session, req: StartRequest, run_dir: Path, context) -> None:
        num_envs = req.num_envs
        ep = await self._run(_policy_episodes, run_dir, req, self.runtime)
        steps = int(ep.steps.max())
        for t in range(steps + 1):
            done = ep.steps <= t if t else np.zeros(num_envs, bool)  # ended after `steps` actions
            frame = pb.PolicyFrame(
                step=t,
                poses=encode(np.concatenate([ep.trajectories[:, t], ep.gif["theta"][:, t, None]], 1)
                             .astype(np.float32)),
                lidar=encode(ep.gif["lidar_ranges"][:, t].astype(np.float32)),
                actions=encode(ep.gif["actions"][:, t - 1] if t else np.zeros((0, 2), np.float32)),
                done=encode(done),
            )  # fmt: skip
            if t == 0:
                frame.goals.CopyFrom(encode(ep.goals.astype(np.float32)))
                frame.walls.CopyFrom(encode(ep.walls.astype(bool)))
            if t == steps:
                frame.success.CopyFrom(encode(ep.success.astype(bool)))
            await context.write(pb.ServerMessage(frame=frame))
        session.episodes = num_envs
        await context.write(
            pb.ServerMessage(
                closed=pb.Closed(steps=steps, env_steps=int(ep.steps.sum()), episodes=num_envs)
            )
        )


def _policy_episodes(run_dir: Path, req: StartRequest, runtime: Runtime):
    """One episode per env of a trained job's policy in the Start's env (its fields on the env it
    trained in), with per-step poses, lidar and actions."""
    from quicknav_core.config import EvalConfig
    from quicknav_core.eval.evaluate import agent_from_run, run_episodes

    agent, _, _ = agent_from_run(run_dir)
    env, params = req.env.build(req.split, runtime)
    cfg = EvalConfig(episodes=req.num_envs, seed=req.seed % 2**31, deterministic=not req.stochastic,
                     gif_episodes=req.num_envs)  # fmt: skip
    return run_episodes(env, params, agent, cfg, runtime=runtime)
