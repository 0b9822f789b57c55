"""Checks python/Cargo.toml's feature pins: every third-party crate the wheel compiles must get
the features the workspace's test build gives it, or maturin's build of the wheel compiles it
(and everything above it) a second time. Prints what to pin and exits 1 when they drifted."""

import collections
import subprocess
import sys


def features(*args):
    """{(crate, version): {feature lists}} as `cargo tree` resolves them for `args`."""
    out = subprocess.run(
        ["cargo", "tree", "-q", "--format", "{p} [{f}]", "--prefix", "none", *args],
        check=True, capture_output=True, text=True,
    ).stdout
    found = collections.defaultdict(set)
    for line in out.splitlines():
        if not line or line.startswith("["):  # "[dev-dependencies]" and such
            continue
        name, version, rest = line.split(" ", 2)
        if "(/" in rest:  # a crate of the workspace: cheap to compile twice
            continue
        found[(name, version)].add(rest.removesuffix(" (*)"))
    return found


wheel = features("-p", "vsgraphs-python", "-e", "normal,build")
tests = features("--workspace", "-e", "normal,build,dev")
# A crate can appear twice (for build scripts and for the code): each of the wheel's copies must
# be one of the tests'.
drift = [(crate, wheel[crate], tests.get(crate, set())) for crate in sorted(wheel)
         if not wheel[crate] <= tests.get(crate, set())]
for (name, version), own, workspace in drift:
    print(f"check-layout: the wheel builds {name} {version} with {sorted(own)}, the tests with "
          f"{sorted(workspace)}: pin the missing features in python/Cargo.toml", file=sys.stderr)
sys.exit(1 if drift else 0)
