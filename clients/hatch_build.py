"""Build hook: generate the gRPC/protobuf Python modules from the .proto files (build output)."""

from __future__ import annotations

from pathlib import Path

from hatchling.builders.hooks.plugin.interface import BuildHookInterface

PROTOS = ["quicknav_client/proto/quicknav/v1/rollout.proto"]


class ProtoBuildHook(BuildHookInterface):
    PLUGIN_NAME = "custom"

    def initialize(self, version: str, build_data: dict) -> None:
        import grpc_tools
        from grpc_tools import protoc

        root = Path(self.root)
        well_known = Path(grpc_tools.__file__).parent / "_proto"
        for proto in PROTOS:
            args = [
                "grpc_tools.protoc",
                f"-I{root}",
                f"-I{well_known}",
                f"--python_out={root}",
                f"--pyi_out={root}",
                f"--grpc_python_out={root}",
                str(root / proto),
            ]
            if protoc.main(args) != 0:
                raise RuntimeError(f"protoc failed on {proto}")
            stem = proto[: -len(".proto")]
            # generated files are git-ignored, so name them for the wheel explicitly
            build_data["artifacts"] += [f"{stem}_pb2.py", f"{stem}_pb2.pyi", f"{stem}_pb2_grpc.py"]
