"""The scenes that ship with clppm (installed as the package clppm.configs)."""
