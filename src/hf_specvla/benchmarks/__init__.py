"""Benchmarks: the toy OpenVLA-style target the demo trains on the spot, and the speed benchmarks (toy scenes and
replayed policy episodes, interleaved against greedy in one process)."""
