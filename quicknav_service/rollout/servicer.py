"""The gRPC ``Rollout`` servicer: one bidirectional stream per agent, one batch of envs per stream.

Protocol (quicknav/v1/rollout.proto): Start -> Started, Step -> Transition, Reset -> ResetDone,
Close -> Closed. Every refused request ends the stream with an exact status code and a message
naming what was wrong and what is allowed; nothing a client sends can take down the server or
another stream. JAX calls run on a thread pool, never on the event loop.
"""

from __future__ import annotations

import asyncio
import json
import logging
import uuid
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import grpc
import numpy as np
from google.protobuf import json_format
from quicknav_client.proto.quicknav.v1 import rollout_pb2 as pb
from quicknav_client.proto.quicknav.v1 import rollout_pb2_grpc as pb_grpc
from quicknav_client.tensors import TensorError, decode, encode

from quicknav_service import auth
from quicknav_service.jobs.limits import check_env, over_limit
from quicknav_service.settings import Settings

log = logging.getLogger("quicknav.rollout")

_SPLITS = {pb.SPLIT_UNSPECIFIED: "train", pb.SPLIT_TRAIN: "train", pb.SPLIT_TEST: "test"}
# Stepping this few envs costs less than the hop to a worker thread; they run inline.
INLINE_MAX_ENVS = 64


# A status message travels in HTTP/2 trailers (metadata): past a few kB it breaks the call.
MAX_MESSAGE_CHARS = 2000


def bounded(message: str) -> str:
    """A status message cut to MAX_MESSAGE_CHARS (bad input is never echoed at length)."""
    if len(message) <= MAX_MESSAGE_CHARS:
        return message
    return message[: MAX_MESSAGE_CHARS - 40] + f"... ({len(message):,} characters in all)"


class Refused(Exception):
    """A request the server refuses: ends the stream with ``code`` and ``message``."""

    def __init__(self, code: grpc.StatusCode, message: str):
        super().__init__(message)
        self.code = code
        self.message = message


# Asynchronous mode: at most this many groups per stream
MAX_GROUPS = 64


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


def _authorization(context: grpc.aio.ServicerContext) -> str | None:
    """The call's ``authorization`` metadata as sent (``Bearer <token>``, as REST takes it)."""
    for key, value in context.invocation_metadata() or ():
        if key.lower() == "authorization" and isinstance(value, str):
            return value
    return None


def _peer_host(context) -> str:
    """The client's address without its port (``ipv4:127.0.0.1:5000`` -> ``127.0.0.1``)."""
    peer = context.peer() or "unknown"
    kind, _, rest = peer.partition(":")
    if kind == "ipv6":
        return rest.rsplit(":", 1)[0].strip("[]")
    return rest.rsplit(":", 1)[0] if kind == "ipv4" else peer


def parse_env_config(start: pb.Start, settings: Settings, base=None):
    """The EnvConfig a Start carries (resolved like every env: fields or dotted keys on ``base``,
    default the defaults), validated against the model and the server's limits."""
    from quicknav_core.config import ConfigError, resolve_env
    from quicknav_core.config.errors import format_items

    which = start.WhichOneof("config")
    if which == "config_json":
        try:
            fields = json.loads(start.config_json or "{}")
        except json.JSONDecodeError as e:
            raise Refused(grpc.StatusCode.INVALID_ARGUMENT,
                          f"start.config_json is not valid JSON ({e})") from None  # fmt: skip
        if not isinstance(fields, dict):
            raise Refused(grpc.StatusCode.INVALID_ARGUMENT,
                          "start.config_json must be a JSON object of EnvConfig fields")  # fmt: skip
    elif which == "config_fields":
        fields = _ints_where_integral(json_format.MessageToDict(start.config_fields))
    else:
        fields = {}
    try:
        config = resolve_env(fields, base)
    except ConfigError as e:
        raise Refused(
            grpc.StatusCode.INVALID_ARGUMENT, format_items(e.items, prefix="start.config")
        ) from None
    problems = check_env(config, settings, lambda field: ["start", "config", field])
    if problems:
        raise Refused(grpc.StatusCode.INVALID_ARGUMENT,
                      "; ".join(f"start.config.{p['msg']}" for p in problems))  # fmt: skip
    return config


def _ints_where_integral(value):
    """protobuf Struct numbers are doubles: give integral ones back as ints (grid_size=8.0 -> 8)."""
    if isinstance(value, dict):
        return {k: _ints_where_integral(v) for k, v in value.items()}
    if isinstance(value, list):
        return [_ints_where_integral(v) for v in value]
    if isinstance(value, float) and value.is_integer() and abs(value) < 2**53:
        return int(value)
    return value


def _box(low: np.ndarray, high: np.ndarray) -> pb.BoxSpec:
    return pb.BoxSpec(dtype="float32", shape=list(low.shape), low=encode(low), high=encode(high))


async def authenticate(settings: Settings, limiter: auth.FailureLimiter, context) -> None:
    """Abort the call unless it carries ``authorization: Bearer <token>`` (when the server has a
    token); failures count per client address, as for REST."""
    token = settings.api_token
    if not token:
        return
    client = _peer_host(context)
    wait = limiter.retry_after(client)
    if wait is not None:
        await context.abort(
            grpc.StatusCode.RESOURCE_EXHAUSTED,
            f"too many failed authentications from this address: retry in {wait} s"
            " (QUICKNAV_AUTH_FAILURES_MAX per QUICKNAV_AUTH_FAILURE_WINDOW_S)",
        )
    if not auth.token_matches(_authorization(context), token):
        limiter.failed(client)
        await context.abort(
            grpc.StatusCode.UNAUTHENTICATED,
            "this server requires the API token: send call metadata"
            " 'authorization: Bearer <token>' (the QUICKNAV_API_TOKEN of the service)",
        )


class RolloutServicer(pb_grpc.RolloutServiceServicer):
    """Serves ``RolloutService.Rollout``; one instance per server, any number of streams."""

    def __init__(self, settings: Settings, executor: ThreadPoolExecutor | None = None):
        self.settings = settings
        self.executor = executor or ThreadPoolExecutor(
            max_workers=min(32, settings.rollout_max_sessions + 2), thread_name_prefix="rollout"
        )
        self.active_sessions = 0
        self.auth_limiter = auth.FailureLimiter(settings.auth_failures_max,
                                                settings.auth_failure_window_s)  # fmt: skip
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
                try:
                    msg = await asyncio.wait_for(context.read(), timeout=idle)
                except TimeoutError:
                    raise Refused(
                        grpc.StatusCode.DEADLINE_EXCEEDED,
                        f"no message for {idle:g} s (QUICKNAV_ROLLOUT_IDLE_S): the session was"
                        " closed; open a new stream and send Start",
                    ) from None
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
        config = parse_env_config(start, s, policy_run[1] if policy_run else None)
        if policy_run and config.obs_dim != policy_run[1].obs_dim:
            trained = policy_run[1]
            raise Refused(
                grpc.StatusCode.INVALID_ARGUMENT,
                f"start.config: the policy of job {start.policy.job_id} reads {trained.obs_dim}-long"
                f" observations (lidar_beams={trained.lidar_beams}, observe_goal="
                f"{trained.observe_goal}); these fields make them {config.obs_dim} long: keep"
                " lidar_beams and observe_goal",
            )
        num_envs = start.num_envs or 1
        if (msg := over_limit("num_envs", num_envs, s, "max_envs")) is not None:
            raise Refused(grpc.StatusCode.RESOURCE_EXHAUSTED, f"start.{msg}")
        message_bytes = 2 * num_envs * config.obs_dim * 4
        if message_bytes > s.grpc_max_message_mb * 2**20:
            raise Refused(
                grpc.StatusCode.RESOURCE_EXHAUSTED,
                f"start.num_envs={num_envs} with obs_dim={config.obs_dim} needs messages of up to"
                f" {message_bytes / 2**20:.1f} MiB; this server allows {s.grpc_max_message_mb} MiB"
                " (QUICKNAV_GRPC_MAX_MESSAGE_MB): use fewer envs or beams per stream",
            )
        if start.split not in _SPLITS:
            raise Refused(
                grpc.StatusCode.INVALID_ARGUMENT,
                f"start.split={start.split}: allowed values are SPLIT_TRAIN (1) and SPLIT_TEST (2)",
            )
        if start.seed >= 2**63:
            raise Refused(
                grpc.StatusCode.INVALID_ARGUMENT,
                f"start.seed={start.seed}: allowed range 0..{2**63 - 1}",
            )
        if self.active_sessions >= s.rollout_max_sessions:
            raise Refused(
                grpc.StatusCode.RESOURCE_EXHAUSTED,
                f"{self.active_sessions} rollout sessions are open, the limit"
                f" (QUICKNAV_ROLLOUT_MAX_SESSIONS) is {s.rollout_max_sessions}: close one or retry"
                " later",
            )
        self.active_sessions += 1
        session.counted = True
        split = _SPLITS[start.split]
        groups = start.groups or 1
        if groups > 1 and policy_run:
            raise Refused(grpc.StatusCode.INVALID_ARGUMENT,
                          "start.groups applies to stepping envs, not to policy mode; send 0")  # fmt: skip
        if groups > min(MAX_GROUPS, num_envs) or num_envs % groups:
            raise Refused(
                grpc.StatusCode.INVALID_ARGUMENT,
                f"start.groups={groups} with num_envs={num_envs}: allowed a divisor of num_envs"
                f" up to {min(MAX_GROUPS, num_envs)} (1 = lock-step)",
            )
        if policy_run:
            if num_envs > s.rollout_policy_max_envs:
                raise Refused(
                    grpc.StatusCode.RESOURCE_EXHAUSTED,
                    f"start.num_envs={num_envs} in policy mode; allowed range"
                    f" 1..{s.rollout_policy_max_envs} (QUICKNAV_ROLLOUT_POLICY_MAX_ENVS)",
                )
            await self._stream_policy(session, start, policy_run[0], config, num_envs, split,
                                      context)  # fmt: skip
            return True

        from quicknav_core.env.batch import BatchedEnv
        from quicknav_core.env.constants import observation_bounds

        def build():
            from quicknav_core.env.rooms import set_bank_cache

            set_bank_cache(s.data_dir / "room-banks")  # a bank is carved once per config
            from quicknav_service.maps import install_resolver

            install_resolver(s)  # a Start may name uploaded maps (map:<id>)
            if groups == 1:
                env = BatchedEnv(config, num_envs, seed=start.seed % 2**32, split=split)
                return env, [], env.reset()
            k = num_envs // groups
            envs = [BatchedEnv(config, k, seed=group_seed(start.seed, g), split=split)
                    for g in range(groups)]  # fmt: skip
            return None, envs, np.concatenate([e.reset() for e in envs])

        session.env, session.groups, obs = await self._run(build)
        session.group_steps = [0] * len(session.groups)
        low, high = observation_bounds(config)
        await context.write(
            pb.ServerMessage(
                started=pb.Started(
                    session_id=session.id,
                    num_envs=num_envs,
                    observation_space=_box(low, high),
                    action_space=_box(-np.ones(2, np.float32), np.ones(2, np.float32)),
                    observations=encode(obs),
                    env_config_json=config.model_dump_json(),
                    max_steps=config.max_steps,
                    groups=groups,
                )
            )
        )
        return False

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
        from quicknav_service.rollout.policy import run_copy

        run_dir = run_copy(self.settings, job_id, "start.policy.job_id") if _is_plain_id(job_id) else None
        if run_dir is None:
            raise Refused(
                grpc.StatusCode.NOT_FOUND,
                f"start.policy.job_id={job_id!r}: no train job with a checkpoint by that id in"
                " this service's artifacts",
            )
        return run_dir, read_config(run_dir).env

    async def _stream_policy(self, session, start, run_dir, config, num_envs, split, context) -> None:
        ep = await self._run(
            _policy_episodes, run_dir, config, num_envs, start.seed % 2**31, split,
            not start.policy.stochastic,
        )  # fmt: skip
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


def _is_plain_id(job_id: str) -> bool:
    return bool(job_id) and all(c.isalnum() or c in "-_" for c in job_id) and len(job_id) <= 64


def _policy_episodes(run_dir: Path, env_config, num_envs: int, seed: int, split: str,
                     deterministic: bool):  # fmt: skip
    """One episode per env of a trained job's policy in ``env_config`` (the Start's fields on the
    env it trained in), with per-step poses, lidar and actions."""
    from quicknav_core.config import EvalConfig
    from quicknav_core.eval.evaluate import agent_from_run, run_episodes

    agent, _, _ = agent_from_run(run_dir)
    env, params = env_config.build(split)
    cfg = EvalConfig(episodes=num_envs, seed=seed, deterministic=deterministic,
                     gif_episodes=num_envs)  # fmt: skip
    return run_episodes(env, params, agent, cfg)
