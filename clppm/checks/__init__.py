"""Checks of a device and of the kernels: the tiny scene through every kernel family (tiny), kernel
probes for tests and benchmarks (testing) and the known-answer self-test child (selftest).
"""
