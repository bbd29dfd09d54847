"""Prints the README's measured table and every figure the README and the guide quote, each computed from its
result file in docs/results/ (total decode time = sum over sum; per call = mean ms per call; see
``hf_specvla.metaworld.comparison.figures``). Reads JSON only, in about a second:

    python examples/metaworld/figures.py
"""

from pathlib import Path

from hf_specvla.metaworld.comparison.figures import report

#: this checkout's result files
RESULTS = Path(__file__).resolve().parents[2] / "docs" / "results"

if __name__ == "__main__":
    print(report(RESULTS))
