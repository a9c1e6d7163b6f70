"""The Rollout port speaks the gRPC conventions other tools expect: grpc.health.v1, server
reflection (what `grpcurl list` uses), and TLS when a certificate is configured; HTTPS likewise."""

from __future__ import annotations

import ssl
import subprocess

import grpc
import httpx
import numpy as np
import pytest
from grpc_health.v1 import health_pb2, health_pb2_grpc
from grpc_reflection.v1alpha.proto_reflection_descriptor_database import (
    ProtoReflectionDescriptorDatabase,
)
from quicknav_client import RolloutClient

from quicknav_service.rollout.server import POLICY_SERVICE, ROLLOUT_SERVICE, BackgroundServer
from quicknav_service.settings import Settings
from tests.service.conftest import free_port, quicknav_process, wait_until_up

SMALL = {"grid_size": 8, "train_rooms": 16, "test_rooms": 8, "lidar_beams": 8}


@pytest.fixture(scope="module")
def self_signed(tmp_path_factory):
    """A self-signed certificate for localhost (openssl, as a user would make one)."""
    folder = tmp_path_factory.mktemp("tls")
    cert, key = folder / "cert.pem", folder / "key.pem"
    subprocess.run(["openssl", "req", "-x509", "-newkey", "rsa:2048", "-nodes", "-days", "2",
                    "-subj", "/CN=localhost", "-addext", "subjectAltName=DNS:localhost",
                    "-keyout", str(key), "-out", str(cert)], check=True, capture_output=True)  # fmt: skip
    return cert, key


def test_health_and_reflection_on_the_rollout_port(tmp_path):
    server = BackgroundServer(Settings(_env_file=None, data_dir=tmp_path, grpc_port=0)).start()
    try:
        with grpc.insecure_channel(f"127.0.0.1:{server.port}") as channel:
            stub = health_pb2_grpc.HealthStub(channel)
            for name in ("", ROLLOUT_SERVICE, POLICY_SERVICE):
                reply = stub.Check(health_pb2.HealthCheckRequest(service=name), timeout=5)
                assert reply.status == health_pb2.HealthCheckResponse.SERVING, name
            with pytest.raises(grpc.RpcError) as e:
                stub.Check(health_pb2.HealthCheckRequest(service="no.such.Service"), timeout=5)
            assert e.value.code() == grpc.StatusCode.NOT_FOUND
            # what `grpcurl -plaintext host:port list` / `describe` ask, through reflection
            db = ProtoReflectionDescriptorDatabase(channel)
            services = set(db.get_services())
            assert {ROLLOUT_SERVICE, POLICY_SERVICE, "grpc.health.v1.Health",
                    "grpc.reflection.v1alpha.ServerReflection"} <= services  # fmt: skip
            from google.protobuf.descriptor_pool import DescriptorPool

            pool = DescriptorPool(db)
            rollout = pool.FindServiceByName(ROLLOUT_SERVICE)
            method = rollout.methods_by_name["Rollout"]
            assert method.input_type.full_name == "quicknav.v1.AgentMessage"
            assert "start" in method.input_type.fields_by_name
            act = pool.FindServiceByName(POLICY_SERVICE).methods_by_name["Act"]
            assert act.input_type.full_name == "quicknav.v1.PolicyRequest"
            assert {"load", "act"} <= set(act.input_type.fields_by_name)
    finally:
        server.stop()


def test_settings__tls_cert_and_key_go_together(tmp_path):
    with pytest.raises(ValueError, match="QUICKNAV_GRPC_TLS_CERT and QUICKNAV_GRPC_TLS_KEY"):
        Settings(_env_file=None, grpc_tls_cert=tmp_path / "c.pem")
    with pytest.raises(ValueError, match="QUICKNAV_TLS_CERT and QUICKNAV_TLS_KEY"):
        Settings(_env_file=None, tls_key=tmp_path / "k.pem")


def test_serve_with_tls__https_api_and_grpc_over_tls(tmp_path, self_signed):
    cert, key = self_signed
    http_port, grpc_port = free_port(), free_port()
    proc = quicknav_process(
        ["serve", "--no-worker", "--port", str(http_port), "--grpc-port", str(grpc_port)],
        QUICKNAV_DATA_DIR=str(tmp_path / "data"), QUICKNAV_TLS_CERT=str(cert),
        QUICKNAV_TLS_KEY=str(key), QUICKNAV_GRPC_TLS_CERT=str(cert), QUICKNAV_GRPC_TLS_KEY=str(key),
    )  # fmt: skip
    url = f"https://localhost:{http_port}"
    try:
        wait_until_up(url, proc, verify=ssl.create_default_context(cafile=str(cert)))
        with pytest.raises(httpx.HTTPError):  # plain HTTP is not spoken on that port
            httpx.get(f"http://localhost:{http_port}/healthz", timeout=2)
        # gRPC over TLS, trusting the self-signed certificate
        with RolloutClient(f"localhost:{grpc_port}", root_certificates=cert.read_bytes()) as rc:
            started = rc.start(num_envs=2, config=SMALL)
            t = rc.step(np.zeros((2, 2), np.float32))
            assert t.observations.shape == started.observations.shape
        # a plaintext client is refused
        with grpc.insecure_channel(f"localhost:{grpc_port}") as channel:
            with pytest.raises(grpc.RpcError) as e:
                health_pb2_grpc.HealthStub(channel).Check(health_pb2.HealthCheckRequest(), timeout=3)
            assert e.value.code() == grpc.StatusCode.UNAVAILABLE
    finally:
        proc.terminate()
        proc.wait(30)
