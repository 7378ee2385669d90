"""Kernels launched by parameter name, checked against their ``__kernel`` declaration.

A kernel's parameter list is read from its declaration in the kernels' source text (object-like
macros such as ``VOLUME_ARGS`` expanded), so a call names every argument::

    k = Kernel(program, "photon_keys")
    k(queue, n, P=params, iface=iface, ..., n=n, kpos=out)     # n work items

and a missing, extra or misspelt name, or a value of the wrong kind (a buffer where a scalar is
declared, a float where an integer is), fails with a message naming the argument before anything
runs.  Python and numpy scalars are converted to the declared type (``uint`` -> ``np.uint32``,
``float`` -> ``np.float32``, ``double`` -> ``np.float64``), as pyopencl's ``GenericScanKernel``
does for its own argument list.  Launch sizes come from :func:`clppm.compute.device.launch`.
"""
from __future__ import annotations

import functools
import re
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from .device import kernel_dir, launch

#: the OpenCL C scalar types a kernel takes by value, and their host types
SCALARS = {"char": np.int8, "uchar": np.uint8, "short": np.int16, "ushort": np.uint16,
           "int": np.int32, "uint": np.uint32, "long": np.int64, "ulong": np.uint64,
           "float": np.float32, "double": np.float64}
_VECTOR = re.compile(r"(char|uchar|short|ushort|int|uint|long|ulong|float|double)(2|3|4|8|16)")
_QUALIFIERS = {"__global", "global", "__constant", "constant", "__local", "local", "__private",
               "private", "const", "volatile", "restrict", "__restrict"}


class KernelArgError(TypeError):
    """A kernel call whose arguments do not match the kernel's declaration."""


@dataclass(frozen=True)
class Param:
    """One kernel parameter: its name, its C type without qualifiers, and whether it is a
    pointer (a buffer, or local memory when ``local``)."""

    name: str
    ctype: str
    pointer: bool = False
    local: bool = False

    @property
    def kind(self) -> str:
        if self.pointer:
            return "local memory" if self.local else "buffer"
        if self.ctype in SCALARS:
            return "scalar"
        return "vector" if _VECTOR.fullmatch(self.ctype) else "struct"

    def convert(self, kernel: str, value):
        """``value`` as the kernel receives it; a :class:`KernelArgError` when it cannot be."""
        kind = self.kind
        what = f"{kernel}: argument {self.name!r} ({self.ctype}{' *' if self.pointer else ''})"
        if kind == "buffer":
            data = getattr(value, "data", value) if _is_array(value) else value
            if not _is_buffer(data):
                raise KernelArgError(f"{what} is a buffer, got {type(value).__name__}")
            return data
        if kind == "local memory":
            return value
        if kind == "scalar":
            return _scalar(what, SCALARS[self.ctype], value)
        if not isinstance(value, (np.ndarray, np.void)) or _is_buffer(value):
            raise KernelArgError(f"{what} is passed by value, got {type(value).__name__}")
        return value


def _is_buffer(v) -> bool:
    import pyopencl as cl
    return isinstance(v, cl.MemoryObjectHolder)


def _is_array(v) -> bool:
    import pyopencl.array as cla
    return isinstance(v, cla.Array)


def _scalar(what: str, t, value):
    """``value`` as the numpy scalar type ``t``: integers for integer and floating types,
    floating values for floating types only, integers within ``t``'s range."""
    if isinstance(value, np.ndarray) and value.ndim == 0:
        value = value[()]
    integral = isinstance(value, (bool, int, np.integer, np.bool_))
    floating = isinstance(value, (float, np.floating))
    if np.issubdtype(t, np.floating):
        if not (integral or floating):
            raise KernelArgError(f"{what} is a scalar, got {type(value).__name__}")
        return t(value)
    if not integral:
        raise KernelArgError(f"{what} is an integer, got {type(value).__name__}")
    info = np.iinfo(t)
    if not info.min <= int(value) <= info.max:
        raise KernelArgError(f"{what}: {int(value)} is outside [{info.min}, {info.max}]")
    return t(int(value))


@dataclass(frozen=True)
class Signature:
    """A kernel's name and its parameters in declaration order."""

    kernel: str
    params: tuple[Param, ...]

    @property
    def names(self) -> tuple[str, ...]:
        return tuple(p.name for p in self.params)

    def bind(self, args: dict) -> list:
        """The positional argument list of a call by name: every parameter named once."""
        missing = [n for n in self.names if n not in args]
        extra = [n for n in args if n not in self.names]
        if missing or extra:
            parts = ([f"missing {', '.join(missing)}"] if missing else []) + \
                    ([f"no parameter named {', '.join(extra)}"] if extra else [])
            raise KernelArgError(f"{self.kernel}: {'; '.join(parts)} "
                                 f"(declared: {', '.join(self.names)})")
        return [p.convert(self.kernel, args[p.name]) for p in self.params]


def strip_comments(src: str) -> str:
    src = re.sub(r"/\*.*?\*/", " ", src, flags=re.S)
    return re.sub(r"//[^\n]*", " ", src)


def object_macros(src: str) -> dict[str, str]:
    """The object-like ``#define NAME body`` macros of ``src`` (continued lines joined)."""
    src = strip_comments(src).replace("\\\n", " ")
    return {m.group(1): m.group(2).strip()
            for m in re.finditer(r"^[ \t]*#[ \t]*define[ \t]+([A-Za-z_]\w*)(?![\w(])[ \t]*(.*)$", src, re.M)}


def expand(text: str, macros: dict[str, str], depth: int = 8) -> str:
    """``text`` with the object-like macros it names replaced by their bodies (nested ones too)."""
    for _ in range(depth):
        new = re.sub(r"\b[A-Za-z_]\w*\b", lambda m: macros.get(m.group(0), m.group(0)), text)
        if new == text:
            return new
        text = new
    raise ValueError(f"macros nested deeper than {depth}: {text[:200]}")


def parse_param(decl: str) -> Param:
    """One parameter declaration: ``__global const float4* pos_w`` -> buffer ``pos_w``."""
    tokens = re.findall(r"[A-Za-z_]\w*|\*", decl)
    words = [t for t in tokens if t != "*"]
    if len(words) < 2:
        raise ValueError(f"cannot read the parameter declaration {decl!r}")
    ctype = " ".join(w for w in words[:-1] if w not in _QUALIFIERS)
    ctype = {"unsigned int": "uint", "unsigned long": "ulong", "unsigned char": "uchar",
             "unsigned short": "ushort"}.get(ctype, ctype)
    return Param(name=words[-1], ctype=ctype, pointer="*" in tokens,
                 local=bool({"__local", "local"} & set(words)))


def kernel_signatures(src: str, macros: dict[str, str]) -> dict[str, Signature]:
    """Every ``__kernel`` declared in ``src``, its parameter list macro-expanded."""
    src = strip_comments(src)
    out = {}
    for m in re.finditer(r"\b__kernel\s+(?:__attribute__\s*\(\(.*?\)\)\s*)?void\s+(\w+)\s*\(([^)]*)\)",
                         src, re.S):
        body = m.group(2)
        if "#" in body:
            raise ValueError(f"{m.group(1)}: preprocessor lines inside the parameter list")
        params = expand(body, macros)
        out[m.group(1)] = Signature(m.group(1), tuple(parse_param(p) for p in params.split(",")
                                                      if p.strip() and p.strip() != "void"))
    return out


@functools.lru_cache(maxsize=None)
def all_signatures(folder: str | None = None) -> dict[str, Signature]:
    """The signatures of every kernel in the ``.cl`` files of ``folder`` (default: the
    package's kernels), with the object-like macros of every source file and header there."""
    d = Path(folder or kernel_dir())
    files = sorted(d.glob("*.h")) + sorted(d.glob("*.cl"))
    macros = {}
    for f in files:
        macros.update(object_macros(f.read_text()))
    out = {}
    for f in sorted(d.glob("*.cl")):
        for name, sig in kernel_signatures(f.read_text(), macros).items():
            if name in out and out[name] != sig:
                raise ValueError(f"kernel {name} is declared twice with different parameters")
            out[name] = sig
    return out


def signature(name: str) -> Signature:
    sigs = all_signatures()
    if name not in sigs:
        raise KeyError(f"no __kernel {name} in {kernel_dir()}")
    return sigs[name]


class Kernel:
    """A built kernel called by parameter name: ``k(queue, size, rows=None, **args)`` launches
    it over ``size`` work items (``rows`` rows of them) with :func:`clppm.compute.device.launch`'s
    sizes."""

    def __init__(self, program, name: str | None = None, *, kernel=None):
        import pyopencl as cl
        self.kernel = kernel if kernel is not None else cl.Kernel(program, name)
        self.signature = signature(self.kernel.function_name)
        clash = {"rows", "want", "start"} & set(self.signature.names)
        if clash:
            raise ValueError(f"{self.name}: parameter {', '.join(sorted(clash))} clashes with a launch option")

    @classmethod
    def wrap(cls, kernel) -> "Kernel":
        """``kernel`` (a ``pyopencl.Kernel`` or already a :class:`Kernel`) called by name."""
        return kernel if isinstance(kernel, cls) else cls(None, kernel=kernel)

    @property
    def name(self) -> str:
        return self.signature.kernel

    def __call__(self, queue, size: int, /, *, rows: int | None = None, want: int = 64, start: int = 0,
                 **args):
        """Launch over ``size`` work items (``rows`` rows of them; ``want``: the local size
        asked for), the first one's global id ``start`` (a tile of a larger range); ``args``
        are the kernel's parameters by name (a parameter may be named ``size`` or ``queue``:
        these two are positional only)."""
        values = self.signature.bind(args)
        g, ls = launch(self.kernel, queue, size, want, rows)
        offset = None if not start else ((int(start),) if rows is None else (int(start), 0))
        return self.kernel(queue, g, ls, *values, global_offset=offset)


def kernels(dev, filename: str, names, defines: dict | None = None) -> dict:
    """``{name: Kernel}`` of the program of ``kernels/filename`` with ``defines`` on ``dev``
    (:meth:`clppm.compute.device.Device.build`), each made once per context by the registry."""
    from .device import DeviceError, fault
    from .programs import REGISTRY, BuildError, BuildSpec
    spec = BuildSpec.of(filename, defines)
    try:
        return {n: REGISTRY.made(dev.ctx, spec, n, lambda prg, n=n: Kernel(prg, n), fault())
                for n in names}
    except BuildError as e:
        raise DeviceError(str(e)) from None
