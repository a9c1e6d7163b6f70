"""A gRPC Rollout stream as a Python object: start a batch of remote envs, step it with numpy.

with RolloutClient("localhost:50051") as rc:
    started = rc.start(num_envs=64, seed=0, config={"grid_size": 8})
    t = rc.step(np.zeros((64, 2), np.float32))
    t.observations, t.rewards, t.terminated, t.truncated, t.final_observations

Asynchronous mode (``groups`` > 1): the server steps one group of envs while the others' messages
travel and the agent computes; ``send`` a group's actions, ``recv`` whichever group is done:

with RolloutClient("localhost:50051") as rc:
    started = rc.start(num_envs=4096, groups=2)        # groups of 2048
    for g in range(2):
        rc.send(policy(rc.group_observations(started.observations, g)), group=g)
    while training:
        t = rc.recv()                                   # t.group: which group stepped
        rc.send(policy(t.observations), group=t.group)
"""

from __future__ import annotations

import json
import queue
import threading
from dataclasses import dataclass
from typing import Any

import grpc
import numpy as np
from google.protobuf import struct_pb2

from quicknav_client.proto.quicknav.v1 import rollout_pb2 as pb
from quicknav_client.proto.quicknav.v1 import rollout_pb2_grpc as pb_grpc
from quicknav_client.tensors import decode, encode

SPLITS = {"train": pb.SPLIT_TRAIN, "test": pb.SPLIT_TEST}
_CLOSE = object()


class RolloutError(Exception):
    """The server refused a request or the stream broke: ``code`` is the gRPC status code."""

    def __init__(self, code: grpc.StatusCode, message: str):
        super().__init__(f"{code.name}: {message}")
        self.code = code
        self.message = message


@dataclass
class Space:
    """A box space: dtype, shape and per-element bounds."""

    dtype: str
    shape: tuple[int, ...]
    low: np.ndarray
    high: np.ndarray


@dataclass
class Started:
    session_id: str
    num_envs: int
    observation_space: Space  # of one env
    action_space: Space  # of one env
    observations: np.ndarray  # (num_envs, obs_dim)
    env_config: dict[str, Any]
    max_steps: int
    groups: int = 1  # asynchronous mode: groups of num_envs / groups envs


@dataclass
class Transition:
    """One step of the batch. Envs that ended are already reset: their last observations are in
    ``final_observations``, row j belonging to env ``done_indices[j]``."""

    observations: np.ndarray  # (n, obs_dim) float32
    rewards: np.ndarray  # (n,) float32
    terminated: np.ndarray  # (n,) bool
    truncated: np.ndarray  # (n,) bool
    done_indices: np.ndarray  # (k,) int32
    final_observations: np.ndarray  # (k, obs_dim) float32
    collisions: np.ndarray  # (n,) bool
    step_count: int
    group: int = 0  # asynchronous mode: the group that stepped (its n = num_envs / groups envs)


@dataclass
class Closed:
    steps: int
    env_steps: int
    episodes: int


@dataclass
class PolicyFrame:
    """One time step of a trained policy's episodes (policy mode)."""

    step: int
    poses: np.ndarray  # (n, 3) x, y, heading
    lidar: np.ndarray  # (n, beams) ranges, metres
    actions: np.ndarray  # (n, 2); empty on step 0
    done: np.ndarray  # (n,)
    goals: np.ndarray | None  # (n, 2) on the first frame
    walls: np.ndarray | None  # (n, g, g) on the first frame
    success: np.ndarray | None  # (n,) on the last frame


def _transition(t: pb.Transition) -> Transition:
    return Transition(
        observations=decode(t.observations),
        rewards=decode(t.rewards),
        terminated=decode(t.terminated),
        truncated=decode(t.truncated),
        done_indices=decode(t.done_indices),
        final_observations=decode(t.final_observations),
        collisions=decode(t.collisions),
        step_count=t.step_count,
        group=t.group,
    )


def _space(spec: pb.BoxSpec) -> Space:
    return Space(spec.dtype, tuple(spec.shape), decode(spec.low), decode(spec.high))


def _metadata(token: str | None):
    return (("authorization", f"Bearer {token}"),) if token else None


class RolloutClient:
    """One Rollout stream (one session). Use as a context manager, or call ``close()``."""

    def __init__(
        self,
        target: str = "127.0.0.1:50051",
        token: str | None = None,
        timeout: float | None = None,
        max_message_mb: int = 256,
        channel: grpc.Channel | None = None,
        tls: bool = False,
        root_certificates: bytes | None = None,
    ):
        """``tls=True`` (or ``root_certificates``, PEM bytes of the CA or a self-signed server
        certificate) speaks TLS to a server started with QUICKNAV_GRPC_TLS_CERT/_KEY."""
        self.target = target
        self.timeout = timeout
        limit = max_message_mb * 2**20
        self._own_channel = channel is None
        options = [
            ("grpc.max_receive_message_length", limit),
            ("grpc.max_send_message_length", limit),
        ]
        if channel is None and (tls or root_certificates is not None):
            creds = grpc.ssl_channel_credentials(root_certificates=root_certificates)
            channel = grpc.secure_channel(target, creds, options=options)
        self._channel = channel or grpc.insecure_channel(target, options=options)
        self._stub = pb_grpc.RolloutServiceStub(self._channel)
        self._outbox: queue.SimpleQueue = queue.SimpleQueue()
        self._responses = self._stub.Rollout(self._requests(), metadata=_metadata(token))
        self._lock = threading.Lock()
        self.started: Started | None = None
        self.closed: Closed | None = None
        self._in_flight: set[int] = set()  # asynchronous mode: groups sent and not received

    def _requests(self):
        while True:
            msg = self._outbox.get()
            if msg is _CLOSE:
                return
            yield msg

    def _call(self, msg: pb.AgentMessage) -> pb.ServerMessage:
        with self._lock:
            self._outbox.put(msg)
            return self._next()

    def _next(self) -> pb.ServerMessage:
        try:
            return next(self._responses)
        except grpc.RpcError as e:
            raise RolloutError(e.code(), e.details() or "") from None
        except StopIteration:
            raise RolloutError(grpc.StatusCode.UNAVAILABLE, "the server ended the stream") from None

    # ------------------------------------------------------------------ protocol
    def start(
        self,
        num_envs: int = 1,
        seed: int = 0,
        config: dict[str, Any] | str | None = None,
        split: str = "train",
        policy_job: str | None = None,
        stochastic: bool = False,
        groups: int = 1,
    ) -> Started | None:
        """Start ``num_envs`` envs with an EnvConfig (a dict of fields or its JSON).

        ``groups`` > 1: asynchronous mode (``send``/``recv``), the envs in that many groups.
        With ``policy_job`` the server streams that job's episodes instead: returns None, read
        them with ``policy_frames()``.
        """
        if split not in SPLITS:
            raise ValueError(f"split={split!r}: allowed values are 'train' and 'test'")
        start = pb.Start(num_envs=num_envs, seed=seed, split=SPLITS[split], groups=groups)
        if isinstance(config, str):
            if not config.lstrip().startswith("{"):  # a preset's name, a file's path
                raise ValueError(f"config={config[:60]!r}: an EnvConfig as a dict of fields or the"
                                 " text of its JSON object; a preset's env is the \"env\" of"
                                 " `quicknav train --preset NAME --print-config`")  # fmt: skip
            start.config_json = config
        elif config:
            fields = struct_pb2.Struct()
            fields.update(json.loads(json.dumps(config)))
            start.config_fields.CopyFrom(fields)
        if policy_job:
            start.policy.CopyFrom(pb.PolicySource(job_id=policy_job, stochastic=stochastic))
            self._outbox.put(pb.AgentMessage(start=start))
            return None  # frames follow: read them with policy_frames()
        reply = self._call(pb.AgentMessage(start=start))
        s = reply.started
        self.started = Started(
            session_id=s.session_id,
            num_envs=s.num_envs,
            observation_space=_space(s.observation_space),
            action_space=_space(s.action_space),
            observations=decode(s.observations),
            env_config=json.loads(s.env_config_json),
            max_steps=s.max_steps,
            groups=max(s.groups, 1),
        )
        return self.started

    def step(self, actions) -> Transition:
        """Step every env; ``actions`` is (num_envs, 2) in [-1, 1] (lock-step sessions)."""
        if self.started is not None and self.started.groups > 1:
            raise RuntimeError("this session is asynchronous (groups > 1): use send() and recv()")
        reply = self._call(pb.AgentMessage(step=pb.Step(actions=encode(actions, "float32"))))
        return _transition(reply.transition)

    # ------------------------------------------------------------------ asynchronous mode
    def group_observations(self, observations: np.ndarray, group: int) -> np.ndarray:
        """Group ``group``'s rows of a whole-batch array (``Started.observations``, a reset's)."""
        k = self.started.num_envs // self.started.groups
        return observations[group * k:(group + 1) * k]

    def send(self, actions, group: int = 0) -> None:
        """Send group ``group``'s actions, (num_envs / groups, 2), without waiting."""
        if group in self._in_flight:
            raise RuntimeError(f"group {group} has a Step in flight: recv() its Transition first")
        self._in_flight.add(group)
        self._outbox.put(pb.AgentMessage(step=pb.Step(actions=encode(actions, "float32"),
                                                      group=group)))  # fmt: skip

    def recv(self) -> Transition:
        """The next group's Transition (whichever group stepped first); ``.group`` says which."""
        if not self._in_flight:
            raise RuntimeError("no Step in flight: send() a group's actions first")
        msg = self._next()
        if msg.WhichOneof("payload") != "transition":
            raise RolloutError(grpc.StatusCode.INTERNAL,
                               f"expected a Transition, got {msg.WhichOneof('payload')}")  # fmt: skip
        t = _transition(msg.transition)
        self._in_flight.discard(t.group)
        return t

    def reset(self, seed: int | None = None) -> np.ndarray:
        """New episodes in every env (same seed, same episodes); returns the first observations."""
        if self._in_flight:
            raise RuntimeError(f"groups {sorted(self._in_flight)} have Steps in flight: recv()"
                               " their Transitions before reset()")  # fmt: skip
        reset = pb.Reset() if seed is None else pb.Reset(seed=seed)
        return decode(self._call(pb.AgentMessage(reset=reset)).reset.observations)

    def policy_frames(self):
        """The frames of a policy-mode stream (after ``start(policy_job=...)``), then Closed."""
        while True:
            msg = self._next()
            kind = msg.WhichOneof("payload")
            if kind == "closed":
                self.closed = Closed(msg.closed.steps, msg.closed.env_steps, msg.closed.episodes)
                self._finish()
                return
            f = msg.frame
            yield PolicyFrame(
                step=f.step,
                poses=decode(f.poses),
                lidar=decode(f.lidar),
                actions=decode(f.actions),
                done=decode(f.done),
                goals=decode(f.goals) if f.HasField("goals") else None,
                walls=decode(f.walls) if f.HasField("walls") else None,
                success=decode(f.success) if f.HasField("success") else None,
            )

    def close(self) -> Closed | None:
        """Close the session (the server replies with totals) and the channel."""
        if self.closed is None and self._responses is not None:
            try:
                while self._in_flight:  # the Transitions of groups in flight come first
                    self.recv()
                reply = self._call(pb.AgentMessage(close=pb.Close()))
                c = reply.closed
                self.closed = Closed(c.steps, c.env_steps, c.episodes)
            except RolloutError:
                pass  # the stream had already ended; nothing to close
        self._finish()
        return self.closed

    def _finish(self) -> None:
        self._outbox.put(_CLOSE)
        if self._responses is not None:
            self._responses.cancel()
            self._responses = None
        if self._own_channel:
            self._channel.close()

    def __enter__(self) -> RolloutClient:
        return self

    def __exit__(self, *exc) -> None:
        self.close()


class RemotePolicy:
    """One ``PolicyService.Act`` stream: a trained job's policy, asked by robots over gRPC.

        with RemotePolicy("127.0.0.1:50051") as rp:
            manifest = rp.load(job_id, rows=2)        # the policy.json of `quicknav export`
            actions = rp.act(observations, start)     # float32 [rows, 2] in [-1, 1]

    The server keeps each row's recurrent state for the stream (reset where ``start`` is true)
    and batches the requests of all streams of a policy together.
    """

    def __init__(self, target: str = "127.0.0.1:50051", token: str | None = None,
                 channel: grpc.Channel | None = None, tls: bool = False,
                 root_certificates: bytes | None = None):  # fmt: skip
        self._own_channel = channel is None
        if channel is None and (tls or root_certificates is not None):
            channel = grpc.secure_channel(target, grpc.ssl_channel_credentials(root_certificates))
        self._channel = channel or grpc.insecure_channel(target)
        self._outbox: queue.SimpleQueue = queue.SimpleQueue()
        stub = pb_grpc.PolicyServiceStub(self._channel)
        self._responses = stub.Act(self._requests(), metadata=_metadata(token))
        self._lock = threading.Lock()
        self.manifest: dict[str, Any] | None = None
        self.rows = 0

    def _requests(self):
        while True:
            msg = self._outbox.get()
            if msg is _CLOSE:
                return
            yield msg

    def _call(self, msg: pb.PolicyRequest) -> pb.PolicyResponse:
        with self._lock:
            self._outbox.put(msg)
            try:
                return next(self._responses)
            except grpc.RpcError as e:
                raise RolloutError(e.code(), e.details() or "") from None
            except StopIteration:
                raise RolloutError(grpc.StatusCode.UNAVAILABLE, "the server ended the stream") from None

    def load(self, job_id: str, rows: int = 1) -> dict[str, Any]:
        """Load a train job's policy for ``rows`` robots; returns its manifest."""
        reply = self._call(pb.PolicyRequest(load=pb.LoadPolicy(job_id=job_id, rows=rows))).loaded
        self.manifest, self.rows = json.loads(reply.manifest_json), reply.rows
        return self.manifest

    def act(self, observations: np.ndarray, start: np.ndarray | None = None) -> np.ndarray:
        """Actions (float32 [rows, 2]) for observations (float32 [rows, obs_dim])."""
        request = pb.ActRequest(observations=encode(np.asarray(observations, np.float32)))
        if start is not None:
            request.start.CopyFrom(encode(np.asarray(start, bool)))
        reply = self._call(pb.PolicyRequest(act=request)).actions
        return decode(reply.actions).copy()

    def close(self) -> None:
        self._outbox.put(_CLOSE)
        if self._own_channel:
            self._channel.close()

    def __enter__(self) -> RemotePolicy:
        return self

    def __exit__(self, *exc) -> None:
        self.close()
