"""The behaviorlib Python client (clients/python).

Its gRPC stubs are generated at build time from the repository's proto/ with
Debian's protoc and grpc_python_plugin (protobuf-compiler-grpc), so nothing
generated is kept in git. Installs without an index into a virtual
environment made with --system-site-packages (Debian's python3-grpcio and
python3-protobuf):

    python3 -m venv --system-site-packages venv
    venv/bin/pip install --no-index clients/python
"""

import glob
import os
import shutil
import subprocess

from setuptools import setup
from setuptools.command.build_py import build_py

HERE = os.path.dirname(os.path.abspath(__file__))
# The protos: the repository's proto/ (pip builds in the source tree), or
# BEHAVIORLIB_PROTO_DIR.
PROTO_DIR = os.environ.get("BEHAVIORLIB_PROTO_DIR", os.path.join(HERE, "..", "..", "proto"))
GOOGLEAPIS_DIR = os.environ.get("BEHAVIORLIB_GOOGLEAPIS_PROTO_DIR",
                                "/usr/share/gocode/src/github.com/gogo/googleapis")


def _tool(name, env):
    path = os.environ.get(env) or shutil.which(name)
    if not path:
        raise RuntimeError(f"{name} not found: install Debian's protobuf-compiler-grpc "
                           f"(or set {env})")
    return path


class BuildWithStubs(build_py):
    """build_py, then the generated modules of every .proto under
    proto/behaviorlib into the build tree (behaviorlib/v1/...)."""

    def run(self):
        super().run()
        protos = sorted(glob.glob(os.path.join(PROTO_DIR, "behaviorlib", "**", "*.proto"),
                                  recursive=True))
        if not protos:
            raise RuntimeError(f"no .proto files under {PROTO_DIR}/behaviorlib "
                               "(set BEHAVIORLIB_PROTO_DIR)")
        protoc = _tool("protoc", "PROTOC")
        plugin = _tool("grpc_python_plugin", "GRPC_PYTHON_PLUGIN")
        out = os.path.abspath(self.build_lib)
        # protoc's own include directory (google/protobuf/*.proto) is found by
        # protoc itself.
        subprocess.run([protoc, f"--proto_path={PROTO_DIR}", f"--python_out={out}",
                        f"--grpc_python_out={out}", f"--plugin=protoc-gen-grpc_python={plugin}",
                        *[os.path.relpath(p, PROTO_DIR) for p in protos]],
                       check=True, cwd=PROTO_DIR)
        # The protos' comments, for the Python behavior systems' descriptions of their
        # parameters (behaviorlib.system.parameters.leading_comment).
        subprocess.run([protoc, f"--proto_path={PROTO_DIR}", "--include_source_info",
                        "--include_imports",
                        f"--descriptor_set_out={os.path.join(out, 'behaviorlib', 'v1', 'descriptors.binpb')}",
                        *[os.path.relpath(p, PROTO_DIR) for p in protos]],
                       check=True, cwd=PROTO_DIR)
        # google.rpc.Status, ErrorInfo and BadRequest (the error details of
        # errors.proto), from Debian's golang-github-gogo-googleapis-dev: a
        # google/rpc package beside google/protobuf (google/ is a namespace).
        rpc_protos = ["google/rpc/status.proto", "google/rpc/error_details.proto"]
        if not os.path.exists(os.path.join(GOOGLEAPIS_DIR, rpc_protos[0])):
            raise RuntimeError(f"{GOOGLEAPIS_DIR}/{rpc_protos[0]} not found: install Debian's "
                               "golang-github-gogo-googleapis-dev (or set "
                               "BEHAVIORLIB_GOOGLEAPIS_PROTO_DIR)")
        subprocess.run([protoc, f"--proto_path={GOOGLEAPIS_DIR}", f"--python_out={out}",
                        *rpc_protos], check=True, cwd=GOOGLEAPIS_DIR)
        open(os.path.join(out, "google", "rpc", "__init__.py"), "w").close()
        # Regular packages for the generated directories.
        for proto in protos:
            directory = os.path.dirname(os.path.relpath(proto, PROTO_DIR))
            while directory and directory != "behaviorlib":
                init = os.path.join(out, directory, "__init__.py")
                if not os.path.exists(init):
                    open(init, "w").close()
                directory = os.path.dirname(directory)


setup(
    name="behaviorlib",
    version="0.1.0",
    description="Python client of behaviorlib: fly robots through the coordinator",
    packages=["behaviorlib", "behaviorlib.system"],
    python_requires=">=3.9",
    # Debian's python3-grpcio and python3-protobuf (not listed as
    # install_requires: pip would look for them on an index).
    cmdclass={"build_py": BuildWithStubs},
)
