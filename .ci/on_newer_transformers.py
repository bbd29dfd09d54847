"""Runs a command only when the installed transformers is newer than the pinned release (tox's ``tflatest``).

    python .ci/on_newer_transformers.py 5.25.0 pytest tests/speculative

When the newest release is the pinned one, ``tf525`` has just run the same tests on it: this prints why it skips
and exits 0. Otherwise it runs the command and exits with its status. Reads the version from the installed
package's metadata (transformers itself is not imported).
"""

from __future__ import annotations

import subprocess
import sys
from importlib.metadata import version

from packaging.version import Version


def main(argv: list[str]) -> int:
    if len(argv) < 2:
        print(__doc__, file=sys.stderr)
        return 2
    pinned, command = Version(argv[0]), argv[1:]
    installed = Version(version("transformers"))
    if installed < pinned:
        print(f"tflatest: transformers {installed} is installed, older than the pinned {pinned}: the upgrade to the "
              "newest release failed", file=sys.stderr)  # fmt: skip
        return 1
    if installed == pinned:
        print(f"tflatest: skipped: the newest transformers release is {installed}, the pinned one, which tf525 tests")
        return 0
    print(f"tflatest: transformers {installed} (newer than the pinned {pinned}): {' '.join(command)}", flush=True)
    return subprocess.run(command).returncode


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
