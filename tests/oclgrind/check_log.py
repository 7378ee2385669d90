"""Read an oclgrind log (``oclgrind --log FILE``): exit 1 on any report from clppm's kernels.

A report is a block of lines, the first unindented (e.g. "Invalid read of size 4 at global
memory address ...", "Read-write data race at ..."), naming its kernel on a "Kernel: NAME" line.

Filtered, with the reason:
  scan_lev1 data races: pyopencl's scan (pyopencl/scan.py, SCAN_INTERVALS_SOURCE) writes its own
  temporary ``partial_scan_buffer`` from every work item, then work item 0 reads the interval's
  last element (``interval_results[GID_0] = partial_scan_buffer[interval_end - 1]``) after only
  ``local_barrier()`` = barrier(CLK_LOCAL_MEM_FENCE), which does not order global memory.  The
  buffer is the scan's own (allocated per call), so this is not clppm's in-place use: an
  out-of-place scan of a fresh array reports the same race (docs/devices.md).
  scan_lev2 data races: pyopencl's second-level scan is launched with its own ``interval_results``
  as both input (interval_sums) and output (partial_scan_buffer) (pyopencl/scan.py, "second level
  scan of per-interval results"); the loads of one unit race with the stores of another.  Seen in
  the radix sort's scan (pyopencl.algorithm.RadixSort), which clppm does not run in place either.

    python tests/oclgrind/check_log.py LOG
"""
import collections
import re
import sys

FILTERED = {("scan_lev1", "data race"): "pyopencl scan: global write read after a local-only barrier",
            ("scan_lev2", "data race"): "pyopencl scan: its second level scans its own interval sums in place"}


def reports(text: str):
    block = []
    for line in text.splitlines() + [""]:
        if line.strip() == "":
            if block:
                yield block
            block = []
        elif not block and line[:1].isspace():
            continue
        else:
            block.append(line)


def main(path: str) -> int:
    with open(path, errors="replace") as f:
        text = f.read().replace("\x00", "")    # oclgrind's worker threads leave NUL holes in the log
    bad, filtered = collections.Counter(), collections.Counter()
    for b in reports(text):
        head = b[0].strip()
        m = next((re.search(r"Kernel:\s*(\S+)", ln) for ln in b if "Kernel:" in ln), None)
        kernel = m.group(1) if m else "?"
        key = next((k for k in FILTERED if k[0] == kernel and k[1] in head), None)
        (filtered if key else bad)[(kernel, re.sub(r"0x[0-9a-f]+", "ADDR", head))] += 1
    for (k, h), n in sorted(filtered.items()):
        why = next(v for x, v in FILTERED.items() if x[0] == k)
        print(f"filtered {n:4d} x {k}: {h}  ({why})")
    for (k, h), n in sorted(bad.items()):
        print(f"REPORT   {n:4d} x {k}: {h}")
    print(f"oclgrind: {sum(bad.values())} reports from clppm's kernels, {sum(filtered.values())} filtered")
    return 1 if bad else 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1]))
