"""``PolicyService.Act``: trained policies served to robots that would rather ask than carry them.

A stream loads one train job's policy for ``rows`` robots, then sends observations and gets
actions. The server keeps each row's recurrent state (reset where ``start`` is true). The Act
calls of every stream of one policy are batched: whatever arrived while the previous batch ran is
concatenated (states included) and run as one jitted call, padded to a power of two rows so a
handful of shapes compile, then split back to the streams.
"""

from __future__ import annotations

import asyncio
import json
import logging
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import grpc
import numpy as np
from quicknav_client.proto.quicknav.v1 import rollout_pb2 as pb
from quicknav_client.proto.quicknav.v1 import rollout_pb2_grpc as pb_grpc
from quicknav_client.tensors import TensorError, decode, encode

from quicknav_core.runtime import Cache, Runtime
from quicknav_core.train.memory import POLICY_MAX_ROWS
from quicknav_service import auth
from quicknav_service.rollout.common import (
    Refused,
    authenticate,
    bounded,
    is_plain_id,
    read_next,
    run_copy,
)
from quicknav_service.settings import Settings

log = logging.getLogger("quicknav.policy")

MAX_ROWS = POLICY_MAX_ROWS  # robots one stream may act for (admission counts a full stream)


def _padded(n: int) -> int:
    return max(8, 1 << (n - 1).bit_length())




class LoadedPolicy:
    """One job's policy with its batcher: the jitted act and the queue of waiting requests."""

    def __init__(self, policy, obs_dim: int, manifest_json: str, executor: ThreadPoolExecutor,
                 max_rows: int = MAX_ROWS):  # fmt: skip
        import jax

        self.policy, self.obs_dim, self.manifest_json = policy, obs_dim, manifest_json
        self.executor = executor
        # rows of one jitted call: the requests waiting together are split into calls of at most
        # this many (one stream's most), so a server with many streams holds what admission
        # counted for one (``policy_memory``), not their sum
        self.max_rows = max_rows
        self.largest_call = 0  # rows of the largest call made, padding included
        self._act = jax.jit(lambda carry, obs, start: policy.act(carry, obs, start, None, True))
        self._pending: list[tuple[Any, np.ndarray, np.ndarray, asyncio.Future]] = []
        self._running = False
        self.batches = 0  # jitted calls made, for tests and /metrics
        self.requests = 0

    def initial(self, rows: int):
        import jax

        return jax.device_get(self.policy.initial_carry(rows))

    async def act(self, carry, obs: np.ndarray, start: np.ndarray):
        """(new carry, actions) for one stream's rows, run in a batch with the other streams'."""
        future = asyncio.get_running_loop().create_future()
        self._pending.append((carry, obs, start, future))
        self.requests += 1
        if not self._running:
            self._running = True
            asyncio.get_running_loop().create_task(self._drain())
        return await future

    async def _drain(self) -> None:
        try:
            while self._pending:
                await asyncio.sleep(0)  # let the requests of this loop iteration join the batch
                batch, rows = [], 0
                while self._pending and (not batch or rows + len(self._pending[0][1]) <= self.max_rows):
                    batch.append(self._pending.pop(0))
                    rows += len(batch[-1][1])
                try:
                    results = await asyncio.get_running_loop().run_in_executor(
                        self.executor, self._run, [(c, o, s) for c, o, s, _ in batch])
                except Exception as e:  # every waiting stream hears of it
                    for *_, future in batch:
                        if not future.done():
                            future.set_exception(e)
                    continue
                for (*_, future), result in zip(batch, results, strict=True):
                    if not future.done():
                        future.set_result(result)
        finally:
            self._running = False

    def _run(self, batch):
        import jax

        sizes = [len(o) for _, o, _ in batch]
        n = sum(sizes)
        pad = _padded(n) - n
        carries = [c for c, _, _ in batch]
        if pad:
            carries.append(self.initial(pad))
        carry = jax.tree.map(lambda *xs: np.concatenate(xs), *carries) if jax.tree.leaves(carries[0]) else ()
        obs = np.concatenate([o for _, o, _ in batch] + [np.zeros((pad, self.obs_dim), np.float32)])
        start = np.concatenate([s for _, _, s in batch] + [np.ones(pad, bool)])
        new_carry, actions = jax.device_get(self._act(carry, obs, start))
        self.batches += 1
        self.largest_call = max(self.largest_call, n + pad)
        out, at = [], 0
        for size in sizes:
            part = jax.tree.map(lambda x, a=at, b=at + size: x[a:b], new_carry)
            out.append((part, np.asarray(actions[at:at + size], np.float32)))
            at += size
        return out


@dataclass
class PolicySession:
    policy: LoadedPolicy | None = None
    rows: int = 0
    carry: Any = None
    steps: int = 0
    counted: bool = field(default=False)


class PolicyServicer(pb_grpc.PolicyServiceServicer):
    """Serves ``PolicyService.Act``; one instance per server, any number of streams."""

    def __init__(self, settings: Settings, executor: ThreadPoolExecutor | None = None,
                 runtime: Runtime | None = None, auth_limiter: auth.Limiter | None = None):  # fmt: skip
        from quicknav_service.runtime import service_runtime

        self.settings = settings
        self.runtime = runtime if runtime is not None else service_runtime(settings)
        self.executor = executor or ThreadPoolExecutor(max_workers=4, thread_name_prefix="policy")
        self.auth_limiter = auth_limiter if auth_limiter is not None else auth.make_limiter(settings)
        # the trained policies kept loaded (networks, jitted act): the least recently loaded go
        # past QUICKNAV_ROLLOUT_POLICY_CACHE; a stream keeps acting with the one it loaded
        self.policies: Cache = Cache(settings.rollout_policy_cache)
        self.active_sessions = 0

    async def Act(self, request_iterator, context: grpc.aio.ServicerContext):
        await authenticate(self.settings, self.auth_limiter, context)
        session = PolicySession()
        idle = self.settings.rollout_idle_s
        try:
            while True:
                msg = await read_next(context, idle, "quicknav.v1.PolicyRequest",
                                      "the stream was closed; open a new one and send load")  # fmt: skip
                if msg is grpc.aio.EOF:
                    return
                kind = msg.WhichOneof("payload")
                if kind == "load":
                    await context.write(await self._load(session, msg.load))
                elif kind == "act":
                    await context.write(await self._act(session, msg.act))
                else:
                    raise Refused(grpc.StatusCode.INVALID_ARGUMENT,
                                  "empty PolicyRequest: set load or act")  # fmt: skip
        except Refused as r:
            await context.abort(r.code, bounded(r.message))
        except asyncio.CancelledError:
            raise
        except Exception as e:
            log.exception("policy stream failed")
            await context.abort(grpc.StatusCode.INTERNAL, bounded(f"{type(e).__name__}: {e}"))
        finally:
            if session.counted:
                self.active_sessions -= 1

    async def _load(self, session: PolicySession, load: pb.LoadPolicy) -> pb.PolicyResponse:
        if session.policy is not None:
            raise Refused(grpc.StatusCode.FAILED_PRECONDITION,
                          "load: this stream has a policy already; open a new stream for another")  # fmt: skip
        rows = load.rows or 1
        if rows > MAX_ROWS:
            raise Refused(grpc.StatusCode.RESOURCE_EXHAUSTED,
                          f"load.rows={rows}: allowed range 1..{MAX_ROWS}")  # fmt: skip
        if self.active_sessions >= self.settings.rollout_max_sessions:
            raise Refused(grpc.StatusCode.RESOURCE_EXHAUSTED,
                          f"the limit of concurrent streams (QUICKNAV_ROLLOUT_MAX_SESSIONS) is"
                          f" {self.settings.rollout_max_sessions}: close one or retry later")  # fmt: skip
        self.active_sessions += 1
        session.counted = True
        loop = asyncio.get_running_loop()
        policy = await loop.run_in_executor(self.executor, self._policy, load.job_id)
        session.policy, session.rows = policy, rows
        session.carry = await loop.run_in_executor(self.executor, policy.initial, rows)
        return pb.PolicyResponse(loaded=pb.PolicyLoaded(
            manifest_json=policy.manifest_json, rows=rows, obs_dim=policy.obs_dim))

    def _policy(self, job_id: str) -> LoadedPolicy:
        run_dir = run_copy(self.runtime, job_id, "load.job_id") if is_plain_id(job_id) else None
        if run_dir is None:
            raise Refused(grpc.StatusCode.NOT_FOUND,
                          f"load.job_id={job_id!r}: no train job with a checkpoint by that id in this"
                          " service's artifacts")  # fmt: skip
        return self.policies.get(job_id, lambda: self._build(run_dir, job_id))

    def _build(self, run_dir: Path, job_id: str) -> LoadedPolicy:
        from quicknav_core.admission import PolicyRequest, admit
        from quicknav_core.export import MANIFEST_FILE, manifest
        from quicknav_core.train.run import load_policy, read_config
        from quicknav_service.jobs.limits import server_limits
        from quicknav_service.rollout.start import describe

        # the door every config passes: this server's limits and memory, before anything loads
        problems = admit(PolicyRequest(read_config(run_dir)), server_limits(self.settings),
                         self.runtime, lambda path: ["load", "policy", *path.split(".")])  # fmt: skip
        if problems:
            code = (grpc.StatusCode.RESOURCE_EXHAUSTED if all(p.get("capacity") for p in problems)
                    else grpc.StatusCode.FAILED_PRECONDITION)  # fmt: skip
            raise Refused(code, f"load.job_id={job_id!r}: " + "; ".join(map(describe, problems)))
        config, policy, meta = load_policy(run_dir)  # the network and its parameters: no trainer
        path = run_dir / MANIFEST_FILE
        text = path.read_text() if path.exists() else json.dumps(
            manifest(config, policy, meta, {"run": job_id, "job_id": job_id}, None))
        return LoadedPolicy(policy, config.env.obs_dim, text, self.executor)

    async def _act(self, session: PolicySession, act: pb.ActRequest) -> pb.PolicyResponse:
        policy = session.policy
        if policy is None:
            raise Refused(grpc.StatusCode.FAILED_PRECONDITION, "act before load: send load(job_id) first")
        rows, dim = session.rows, policy.obs_dim
        try:
            obs = decode(act.observations)
            start = decode(act.start) if act.HasField("start") else np.zeros(rows, bool)
        except TensorError as e:
            raise Refused(grpc.StatusCode.INVALID_ARGUMENT, f"act: {e}") from None
        if obs.dtype != np.float32 or obs.shape != (rows, dim):
            raise Refused(grpc.StatusCode.INVALID_ARGUMENT,
                          f"act.observations: expected a float32 tensor of shape [{rows}, {dim}], got"
                          f" {obs.dtype} {list(obs.shape)}")  # fmt: skip
        if not np.isfinite(obs).all():
            raise Refused(grpc.StatusCode.INVALID_ARGUMENT, "act.observations: NaN or infinite entries")
        if start.dtype != np.bool_ or start.shape != (rows,):
            raise Refused(grpc.StatusCode.INVALID_ARGUMENT,
                          f"act.start: expected a bool tensor of shape [{rows}], got {start.dtype}"
                          f" {list(start.shape)}")  # fmt: skip
        session.carry, actions = await policy.act(session.carry, obs, start)
        session.steps += 1
        return pb.PolicyResponse(actions=pb.ActResponse(actions=encode(actions), step=session.steps))
