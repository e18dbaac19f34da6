"""What a command used: run it as a child and print, as JSON, the CPU seconds and the largest
resident memory of it and every process it waited for (Dask's workers included), and its wall time.

    python benchmarks/usage.py -- twray study ...

The estimates twray checked before running are read from the file TWRAY_ESTIMATES names
(pipeline/limits.py); benchmarks/bench_estimates.py sets both side by side.
"""

import json
import resource
import subprocess
import sys
import time


def main(argv: list[str]) -> int:
    cmd = argv[argv.index("--") + 1:] if "--" in argv else argv
    t0 = time.perf_counter()
    proc = subprocess.run(cmd, capture_output=True, text=True)
    wall = time.perf_counter() - t0
    use = resource.getrusage(resource.RUSAGE_CHILDREN)
    print(json.dumps({"rc": proc.returncode, "wall_s": wall, "cpu_s": use.ru_utime + use.ru_stime,
                      "peak_rss": use.ru_maxrss * 1024, "stdout": proc.stdout[-2000:],
                      "stderr": proc.stderr[-2000:]}))
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
