"""The Docker runtime stage installs enough: every shared library that a
binary of the image (deploy/compose/Dockerfile: the channel broker, the
simulator, the coordinator, the console, behaviorctl and every behavior
system) needs directly comes from a package of `scripts/install-deps.sh
--runtime`, from one whose libraries deploy/compose/copy-libraries.sh copies
from the build stage (OpenCV's, decision 38), or from libc6, which every
Debian image has; so does every library that a copied library needs
directly. Each installed package exists in the configured Debian archive.
(The image's build also checks with ldd that nothing is missing.)

    /usr/bin/python3 tests/deploy/runtime_packages_test.py --build-dir build
"""

import argparse
import os
import re
import subprocess
import sys
import unittest

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
import deploy_support as ds  # noqa: E402

BUILD_DIR = ds.DEFAULT_BUILD_DIR
BASE_IMAGE_PACKAGES = {"libc6"}


def runtime_packages():
    with open(os.path.join(ds.REPO, "scripts", "install-deps.sh")) as f:
        text = f.read()
    match = re.search(r'^RUNTIME_PACKAGES="([^"]*)"', text, re.MULTILINE)
    assert match, "RUNTIME_PACKAGES not found in scripts/install-deps.sh"
    return set(match.group(1).replace("\\\n", " ").split())


def copied_packages():
    with open(os.path.join(ds.REPO, "deploy", "compose", "copy-libraries.sh")) as f:
        text = f.read()
    match = re.search(r'^COPIED_PACKAGES="([^"]*)"', text, re.MULTILINE)
    assert match, "COPIED_PACKAGES not found in deploy/compose/copy-libraries.sh"
    return set(match.group(1).replace("\\\n", " ").split())


def needed_libraries(binary):
    """{soname: resolved path} of the libraries `binary` names directly."""
    dynamic = subprocess.run(["objdump", "-p", binary], capture_output=True, text=True,
                             check=True).stdout
    needed = re.findall(r"^\s+NEEDED\s+(\S+)$", dynamic, re.MULTILINE)
    resolved = {}
    for line in subprocess.run(["ldd", binary], capture_output=True, text=True,
                               check=True).stdout.splitlines():
        match = re.match(r"\s*(\S+) => (\S+)", line)
        if match:
            resolved[match.group(1)] = match.group(2)
        # The loader itself: "/lib64/ld-linux-x86-64.so.2 (0x...)".
        match = re.match(r"\s*(/\S+/([^/\s]+)) \(0x", line)
        if match:
            resolved.setdefault(match.group(2), match.group(1))
    return {name: resolved.get(name) for name in needed}


def owning_packages(paths):
    """{path: the Debian package that installed it} (merged-/usr aware), in
    one dpkg -S call."""
    candidates = {}
    for path in paths:
        real = os.path.realpath(path)
        for p in (path, real):
            candidates.setdefault(path, []).append(p)
            candidates[path].append(p[4:] if p.startswith("/usr/") else "/usr" + p)
    queried = sorted({c for cs in candidates.values() for c in cs})
    result = subprocess.run(["dpkg", "-S", *queried], capture_output=True, text=True)
    owner = {}
    for line in result.stdout.splitlines():
        package, _, owned = line.partition(": ")
        owner[owned.strip()] = package.split(":")[0].strip()
    return {path: next((owner[c] for c in cs if c in owner), None)
            for path, cs in candidates.items()}


class RuntimePackagesTest(unittest.TestCase):
    def binaries(self):
        names = ds.INFRASTRUCTURE_PROGRAMS + ds.behavior_systems_in_source()
        paths = {name: ds.build_binary(BUILD_DIR, name) for name in names}
        missing = [p for p in paths.values() if not os.access(p, os.X_OK)]
        self.assertEqual(missing, [], f"not built (build {BUILD_DIR} first)")
        return paths

    def test_runtime_packages_cover_every_library_the_binaries_need(self):
        installed, copied = runtime_packages(), copied_packages()
        self.assertTrue(installed)
        self.assertTrue(copied)
        self.assertEqual(installed & copied, set(), "both installed and copied")
        packages = installed | copied
        needed = {name: needed_libraries(binary) for name, binary in self.binaries().items()}
        owners = owning_packages({path for libs in needed.values() for path in libs.values()
                                  if path})
        # What the copied libraries need in turn, down to the last one.
        pending = {path for path, package in owners.items() if package in copied}
        while pending:
            path = pending.pop()
            needed[os.path.basename(path)] = needed_libraries(path)
            new = {p for p in needed[os.path.basename(path)].values() if p and p not in owners}
            owners.update(owning_packages(new))
            pending |= {p for p in new if owners[p] in copied}
        for name, libraries in needed.items():
            for soname, path in libraries.items():
                with self.subTest(binary=name, library=soname):
                    self.assertIsNotNone(path, f"{soname} does not resolve")
                    package = owners[path]
                    self.assertIsNotNone(package, f"no Debian package owns {path}")
                    self.assertIn(package, packages | BASE_IMAGE_PACKAGES,
                                  f"{name} needs {soname} from {package}, which "
                                  f"install-deps.sh --runtime does not install and "
                                  f"copy-libraries.sh does not copy")

    def test_runtime_packages_exist(self):
        packages = sorted(runtime_packages())
        result = subprocess.run(["apt-cache", "show", "--no-all-versions", *packages],
                                capture_output=True, text=True)
        shown = set(re.findall(r"^Package: (\S+)$", result.stdout, re.MULTILINE))
        self.assertEqual(set(packages) - shown, set(),
                         f"not in the Debian archive (apt-get update?): {result.stderr.strip()}")

if __name__ == "__main__":
    parser = argparse.ArgumentParser()
    parser.add_argument("--build-dir", default=BUILD_DIR)
    args, rest = parser.parse_known_args()
    BUILD_DIR = os.path.abspath(args.build_dir)
    unittest.main(argv=[sys.argv[0], *rest], verbosity=2)
