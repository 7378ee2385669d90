"""OpenCL underneath everything: the ICD loader setup (icd), the device and its kernel builds
(device), the parent side of a device's known-answer self-test (devicecheck), a kernel launched
by parameter name (kernelcall), the kernels' structs and constants as numpy dtypes and dicts
(structs, constants).
"""
