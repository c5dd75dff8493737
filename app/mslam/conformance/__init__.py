"""Conformance: the reference as a checker of any implementation of the kernels.

``mslam conformance export DIR`` writes golden cases (inputs, ``mslam_ref`` outputs,
tolerances, conventions) as uncompressed ``.npz`` files and a JSON index
(:mod:`mslam.conformance.export`); ``mslam conformance check DIR --impl MODULE|ADAPTER.py``
runs an implementation on them and prints a verdict per kernel
(:mod:`mslam.conformance.check`). docs/conformance.md shows both and a C++ reader.

Modules: tolerances, kernels, cases, export, adapter, check.
"""
