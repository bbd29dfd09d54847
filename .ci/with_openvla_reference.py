"""Runs the OpenVLA parity tests when the official reference is beside the checkout (tox's ``openvla``).

    python .ci/with_openvla_reference.py ../shared/openvla-reference pytest tests/openvla/test_openvla_parity.py -rs

With the reference folder (the official OpenVLA code and its fixture builder; CI has it as ../shared/openvla-reference):
runs its ``make_fixture.sh`` (which builds the fixture where ``OPENVLA_REF_WORK`` says), then the command, and exits
with the first failing status. Without it (a fresh clone): prints why it skips and exits 0, so that the README's test
command passes where the reference cannot be; every other environment runs without it. ``OPENVLA_REFERENCE_REQUIRED=1``
makes a missing reference an error (exit 1) instead, for a CI that must not skip the parity tests.
"""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

#: what builds the fixture inside the reference folder
FIXTURE_BUILDER = "make_fixture.sh"
#: set to 1 to fail, not skip, without the reference
REQUIRED_VARIABLE = "OPENVLA_REFERENCE_REQUIRED"


def main(argv: list[str]) -> int:
    if len(argv) < 2:
        print(__doc__, file=sys.stderr)
        return 2
    reference, command = Path(argv[0]), argv[1:]
    if not reference.is_dir():
        why = (
            f"no OpenVLA reference at {reference} (the official OpenVLA code and its fixture builder, which CI "
            f"provides beside the checkout as ../shared/openvla-reference; another folder: OPENVLA_REFERENCE=<it>)"
        )
        if os.environ.get(REQUIRED_VARIABLE, "") not in ("", "0"):
            print(f"openvla: {why}, and {REQUIRED_VARIABLE} is set: the parity tests must run", file=sys.stderr)
            return 1
        print(f"openvla: skipped: {why}: the parity tests against the official code need it")
        return 0
    builder = reference / FIXTURE_BUILDER
    if not builder.is_file():
        print(f"openvla: {reference} has no {FIXTURE_BUILDER}: not the OpenVLA reference folder", file=sys.stderr)
        return 1
    print(f"openvla: the reference is at {reference}: bash {builder}, then {' '.join(command)}", flush=True)
    built = subprocess.run(["bash", str(builder)]).returncode
    if built:
        return built
    return subprocess.run(command).returncode


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
