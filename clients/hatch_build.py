"""Build hook: generate the gRPC/protobuf Python modules from the one .proto (build output).

The proto's one home is the repository's ``proto/quicknav/v1/rollout.proto``; an sdist carries a
copy at ``proto/`` beside this file. protoc runs on a temporary tree that mirrors the Python
package, so the generated modules import each other as ``quicknav_client.proto.quicknav.v1``.
"""

from __future__ import annotations

import shutil
import tempfile
from pathlib import Path

from hatchling.builders.hooks.plugin.interface import BuildHookInterface

PROTOS = ["quicknav/v1/rollout.proto"]  # relative to the proto root
PACKAGE = Path("quicknav_client/proto")  # where the generated modules live


def proto_root(root: Path) -> Path:
    """The proto tree: the repository's (a checkout) or the sdist's copy."""
    for candidate in (root.parent / "proto", root / "proto"):
        if (candidate / PROTOS[0]).is_file():
            return candidate
    raise FileNotFoundError(f"no {PROTOS[0]} under {root.parent / 'proto'} or {root / 'proto'}")


class ProtoBuildHook(BuildHookInterface):
    PLUGIN_NAME = "custom"

    def initialize(self, version: str, build_data: dict) -> None:
        import grpc_tools
        from grpc_tools import protoc

        root = Path(self.root)
        source = proto_root(root)
        well_known = Path(grpc_tools.__file__).parent / "_proto"
        with tempfile.TemporaryDirectory() as tmp:
            for proto in PROTOS:
                staged = Path(tmp) / PACKAGE / proto
                staged.parent.mkdir(parents=True, exist_ok=True)
                shutil.copyfile(source / proto, staged)
                args = [
                    "grpc_tools.protoc",
                    f"-I{tmp}",
                    f"-I{well_known}",
                    f"--python_out={root}",
                    f"--pyi_out={root}",
                    f"--grpc_python_out={root}",
                    str(staged),
                ]
                if protoc.main(args) != 0:
                    raise RuntimeError(f"protoc failed on {source / proto}")
                stem = (PACKAGE / proto).as_posix()[: -len(".proto")]
                # generated files are git-ignored, so name them for the wheel explicitly
                build_data["artifacts"] += [
                    f"{stem}_pb2.py", f"{stem}_pb2.pyi", f"{stem}_pb2_grpc.py"
                ]  # fmt: skip
