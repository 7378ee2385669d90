"""Register OpenCL drivers installed from pip with the ICD loader, before it starts.

pyopencl's wheel ships the ocl-icd loader, which reads its list of drivers once, at the first
platform query: the ``.icd`` files in ``OCL_ICD_VENDORS`` (default ``/etc/OpenCL/vendors``) and,
always, those in pyopencl's own ``.libs`` folder (``PYOPENCL_HOME``; that is how PoCL's pip
package, bundled in pyopencl's wheel, is found). This loader does not honour
``OCL_ICD_FILENAMES``.

Intel's CPU runtime from pip (``intel-opencl-rt``, the ``clppm[intel]`` extra) puts
``libintelocl.so`` into the environment's ``lib/``, but its packaged
``etc/OpenCL/vendors/intel-cpu.icd`` names a build-machine placeholder
(``/opt/anaconda1anaconda2anaconda3/lib/libintelocl.so``), so the loader finds nothing.
:func:`register` writes a vendors folder holding an ``.icd`` with the real path plus links to
every ``.icd`` of the folder the loader would otherwise read (so system drivers stay visible),
and points ``OCL_ICD_VENDORS`` at it. No ``LD_LIBRARY_PATH`` is needed: ``libintelocl.so`` has
``RUNPATH $ORIGIN`` and finds libimf, libsvml, libtbb and its kernel libraries beside itself.

It runs when clppm is imported (``clppm/__init__.py``), which is before any clppm code queries
platforms; a program that queries platforms through pyopencl before importing clppm sees the
drivers the loader found then.  ``CLPPM_NO_ICD=1`` turns it off.
"""
from __future__ import annotations

import hashlib
import os
import sys
import tempfile

SYSTEM_VENDORS = "/etc/OpenCL/vendors"


def intel_cpu_library() -> str | None:
    """Path of the pip-installed ``libintelocl.so`` in this environment, or None."""
    p = os.path.join(sys.prefix, "lib", "libintelocl.so")    # where pip puts it: no metadata scan
    if os.path.isfile(p):
        return os.path.realpath(p)
    try:
        from importlib import metadata
        files = metadata.files("intel-opencl-rt") or []
    except Exception:                 # not installed (PackageNotFoundError) or no RECORD
        files = []
    for f in files:
        if f.name == "libintelocl.so":
            p = os.path.realpath(f.locate())
            if os.path.isfile(p):
                return p
    return None


def _icd_entries(folder: str) -> dict[str, str]:
    """``name -> library`` of the ``.icd`` files in ``folder`` (unreadable ones skipped)."""
    out = {}
    try:
        names = sorted(os.listdir(folder))
    except OSError:
        return out
    for n in names:
        if n.endswith(".icd"):
            try:
                with open(os.path.join(folder, n), encoding="utf-8", errors="replace") as f:
                    out[n] = f.read().strip()
            except OSError:
                pass
    return out


def _cache_dir(key: str) -> str:
    base = os.environ.get("XDG_CACHE_HOME") or os.path.join(os.path.expanduser("~"), ".cache")
    for root in (os.path.join(base, "clppm"), os.path.join(tempfile.gettempdir(), f"clppm-{os.getuid()}")):
        d = os.path.join(root, "icd-" + key)
        try:
            os.makedirs(d, exist_ok=True)
            return d
        except OSError:
            continue
    raise OSError("no writable cache folder for the OpenCL vendors list")


def _write_vendors(lib: str, previous: str, entries: dict[str, str]) -> str:
    """A folder with ``clppm-intel-cpu.icd`` naming ``lib`` and links to ``previous``'s ``.icd``s."""
    key = hashlib.sha1("\0".join([lib, previous, *sorted(entries)]).encode()).hexdigest()[:12]
    d = _cache_dir(key)
    want = {"clppm-intel-cpu.icd": None, **{n: os.path.join(previous, n) for n in entries}}
    for n in os.listdir(d):                           # drop what an older run left behind
        if n not in want:
            os.remove(os.path.join(d, n))
    for n, src in want.items():
        p = os.path.join(d, n)
        if src is None:
            tmp = f"{p}.{os.getpid()}"
            with open(tmp, "w", encoding="utf-8") as f:
                f.write(lib + "\n")
            os.replace(tmp, p)                         # atomic: parallel processes see a whole file
        elif not os.path.islink(p) or os.readlink(p) != src:
            tmp = f"{p}.{os.getpid()}"
            os.symlink(src, tmp)
            os.replace(tmp, p)
    return d


#: the pip packages of Intel's CPU runtime (the ``clppm[intel]`` extra)
INTEL_DISTS = ("intel-opencl-rt", "intel-cmplr-lib-rt", "tbb")


def link_duplicates(paths: list[str]) -> int:
    """Make byte-identical copies of one shared library a single file: ``paths`` grouped by the
    name before ``.so`` and the size, every copy whose bytes equal the group's first file is
    replaced by a hard link to it (atomically: a link under a temporary name, then renamed over
    the copy; a running process keeps the file it mapped).  Returns the bytes freed.

    Wheels cannot hold symbolic links, so Intel's runtime installs ``libX.so``, ``libX.so.1``
    and ``libX.so.1.2.3`` as two or three copies of the same library: 324 MB of its 600 MB.
    The files keep their names and bytes (pip's RECORD still matches; ``pip uninstall`` removes
    every name), so nothing that loads them can tell."""
    import filecmp
    groups: dict = {}
    for p in paths:
        try:
            st = os.lstat(p)
        except OSError:
            continue
        name = os.path.basename(p)
        if ".so" not in name or not os.path.isfile(p) or os.path.islink(p):
            continue
        groups.setdefault((os.path.dirname(p), name.split(".so")[0], st.st_size), []).append(p)
    freed = 0
    for (folder, _, size), files in groups.items():
        first, *rest = sorted(files, key=len, reverse=True)     # the fully versioned name stays
        for p in rest:
            tmp = f"{p}.clppm-{os.getpid()}"
            try:
                if os.path.samefile(first, p) or not filecmp.cmp(first, p, shallow=False):
                    continue
                os.link(first, tmp)
                os.replace(tmp, p)
                freed += size
            except OSError:                       # read-only, another file system: leave it
                if os.path.lexists(tmp):
                    os.remove(tmp)
    return freed


def _runtime_files() -> list[str]:
    """The shared libraries that Intel's runtime's pip packages installed."""
    from importlib import metadata
    out = []
    for dist in INTEL_DISTS:
        try:
            files = metadata.files(dist) or []
        except Exception:             # not installed (PackageNotFoundError) or no RECORD
            continue
        out += [str(f.locate()) for f in files if ".so" in f.name]
    return out


def shrink_runtime(lib: str) -> None:
    """Once per installed runtime (a marker in clppm's cache folder, keyed by the library's path,
    size and time): :func:`link_duplicates` over its packages' libraries."""
    try:
        st = os.stat(lib)
        key = hashlib.sha1(f"{lib}\0{st.st_size}\0{st.st_mtime_ns}".encode()).hexdigest()[:12]
        marker = os.path.join(_cache_dir("linked"), key)
        if os.path.exists(marker):
            return
        link_duplicates(_runtime_files())
        open(marker, "w").close()
    except OSError:
        pass


def register() -> str | None:
    """Point the ICD loader at the pip-installed Intel CPU runtime; the vendors folder, or None.

    Nothing is done when the runtime is not installed, when ``CLPPM_NO_ICD`` is set, or when the
    folder the loader reads already lists a ``libintelocl.so`` (a system-wide install)."""
    if os.environ.get("CLPPM_NO_ICD"):
        return None
    lib = intel_cpu_library()
    if lib is None:
        return None
    shrink_runtime(lib)
    previous = os.environ.get("OCL_ICD_VENDORS") or SYSTEM_VENDORS
    if not os.path.isdir(previous):                  # ocl-icd also takes a single .icd file
        return None if os.path.exists(previous) else _point(lib, previous, {})
    entries = _icd_entries(previous)
    if any(os.path.basename(v) == "libintelocl.so" for v in entries.values()):
        return None
    return _point(lib, previous, entries)


def _point(lib: str, previous: str, entries: dict[str, str]) -> str | None:
    try:
        d = _write_vendors(lib, previous, entries)
    except OSError:
        return None                                   # read-only home and /tmp: PoCL still works
    os.environ["OCL_ICD_VENDORS"] = d
    return d


def owned_pocl_cache() -> str:
    """The PoCL kernel cache folder clppm owns (below its own cache folder)."""
    base = os.environ.get("XDG_CACHE_HOME") or os.path.join(os.path.expanduser("~"), ".cache")
    return os.path.join(base, "clppm", "pocl-kcache")


def own_pocl_cache() -> None:
    """Give PoCL a kernel cache of clppm's own (``POCL_CACHE_DIR``) unless the user chose one, so
    that clppm can drop it whole when a crashed compile left a broken entry there (PoCL then
    "builds" programs without kernels from it).  PoCL reads the variable when it starts.  Its
    broken entries go first (:func:`prune_pocl_cache`): PoCL 3.1 asserts on one, 3.0 aborts."""
    if not os.environ.get("POCL_CACHE_DIR"):
        os.environ["POCL_CACHE_DIR"] = owned_pocl_cache()
    prune_pocl_cache(os.environ["POCL_CACHE_DIR"])


#: the first bytes of LLVM bitcode, bare and wrapped: what PoCL keeps as a program.bc
_BITCODE = (b"BC\xc0\xde", b"\xde\xc0\x17\x0b")


#: PoCL writes a program's entry through ``tempfile_*`` files and fills its folder while it
#: compiles: an entry younger than this may belong to a build running in another process
STALE_S = 600.0


def prune_pocl_cache(d: str, stale_s: float = STALE_S) -> None:
    """Drop the entries of PoCL's kernel cache ``d`` that a crashed compile leaves: programs
    whose ``program.bc`` is not LLVM bitcode (truncated, garbage), and ``tempfile_*`` files or
    program folders without a ``program.bc`` older than ``stale_s`` seconds (younger ones may be
    another process's build in progress)."""
    import shutil
    import time
    now = time.time()

    def old(p):
        try:
            return now - os.path.getmtime(p) > stale_s
        except OSError:
            return False

    def drop(p):
        if os.path.isdir(p):
            shutil.rmtree(p, ignore_errors=True)
        else:
            try:
                os.remove(p)
            except OSError:
                pass
    try:
        tops = os.listdir(d)
    except OSError:
        return
    for top in tops:
        p = os.path.join(d, top)
        if top.startswith("tempfile_"):
            if old(p):
                drop(p)
            continue
        try:
            subs = os.listdir(p) if os.path.isdir(p) else []
        except OSError:
            continue
        for sub in subs:
            entry = os.path.join(p, sub)
            bc = os.path.join(entry, "program.bc")
            if os.path.exists(bc) and not _bitcode(bc) or not os.path.exists(bc) and old(entry):
                drop(entry)


def _bitcode(path: str) -> bool:
    try:
        with open(path, "rb") as f:
            return f.read(4) in _BITCODE
    except OSError:
        return False
