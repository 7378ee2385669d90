"""The tiny scene through every kernel family on the first device (under oclgrind: its own).

    python tests/oclgrind/tiny_all.py [PHOTONS [WxH]]
"""
import sys
import time

from clppm.compute import device
from clppm.checks import tiny

t0 = time.perf_counter()
dev = device.open_device(None)
print(f"device: {dev.name} ({device.implementation(dev.device)})", flush=True)
photons = int(sys.argv[1]) if len(sys.argv) > 1 else 2000
res = tuple(int(v) for v in (sys.argv[2] if len(sys.argv) > 2 else "8x6").split("x"))
secs = tiny.run_all(dev, photons=photons, resolution=res)
for k, v in secs.items():
    print(f"  {v:7.1f} s  {k}", flush=True)
rows = device.launched(dev.device)
ran = {r["kernel"] for r in rows}
print("kernels launched (local size / work-group limit): "
      + ", ".join(f"{r['kernel']} {r['local_size']}/{r['work_group_size']}" for r in rows))
print(f"total {time.perf_counter() - t0:.1f} s")
missing = set(tiny.KERNELS) - ran
if missing:
    sys.exit(f"the tiny scene did not launch {sorted(missing)}")
