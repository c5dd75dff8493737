"""Taichi-scope building blocks (@ti.func) shared by the fast kernels."""
