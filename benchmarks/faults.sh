#!/usr/bin/env bash
# Fault injection: damage, kill, interrupt and abuse twray, and print what happened.
# Usage: benchmarks/faults.sh  (after make install; works in a temporary folder)
set -u
ROOT=$(cd "$(dirname "$0")/.." && pwd)
TW=${TW:-$ROOT/.venv/bin/twray}
PY=${PY:-$ROOT/.venv/bin/python}
W=$(mktemp -d /tmp/faults.XXXX); cd $W
cat > s.yaml <<'Y'
title: faults
preset: birch
seed: 3
rays: 400
beam_um: 100
thickness_mm: 0.3
trace: {method: fast}
vary:
  parameter: delta_ri
  values: [-0.02, 0.02]
Y
run() { echo "\$ twray $*"; "$TW" "$@" > out.txt 2> err.txt; rc=$?; echo "  exit $rc; stderr lines $(wc -l < err.txt): $(tail -1 err.txt | cut -c1-200)"; }
show() { grep "delta_ri=" out.txt | sed 's/^/  /'; }
S="study s.yaml --scale small --cache c --results r --workers 1"
run $S; show; cp out.txt ref.txt
echo "## kill -9 mid-run, then rerun"; rm -rf c r
setsid "$TW" $S > /dev/null 2>&1 & P=$!; sleep 6; kill -9 -- -$P 2>/dev/null; sleep 1  # the run and its workers
echo "  left: $(find c r -name '.*' 2>/dev/null | wc -l) hidden temporary files"
run $S; show; cmp -s <(grep delta_ri= out.txt) <(grep delta_ri= ref.txt) && echo "  identical to the undamaged run"
echo "  left after rerun: $(find c r -name '.*' 2>/dev/null | wc -l)"
echo "## damage: flip a byte in a wood chunk + swap the two ray files + edit a summary + change the result"
"$PY" - <<'P'
import json, pathlib, zarr
c = pathlib.Path("c")
ch = sorted((c/"micro").rglob("c/*/*/*"))[0]; b = bytearray(ch.read_bytes()); b[len(b)//2] ^= 1; ch.write_bytes(bytes(b))
rays = sorted((c/"rays").glob("*.npz")); a, bb = rays[0].read_bytes(), rays[1].read_bytes(); rays[0].write_bytes(bb); rays[1].write_bytes(a)
s = sorted((c/"summary").glob("*.json"))[0]; r = json.loads(s.read_text()); r["value"]["fwhm_r_deg"] = 99.0; s.write_text(json.dumps(r))
z = zarr.open_array("r/s.zarr/FWHM_R", mode="r+"); z[0] = 42.0
P
run $S; show; sed 's/^/    /' err.txt; grep -c "is damaged" err.txt | sed 's/^/  damage warnings: /'; cmp -s <(grep delta_ri= out.txt) <(grep delta_ri= ref.txt) && echo "  identical to the undamaged run"
echo "## an entry that no longer decodes"
for f in c/rays/*.npz; do head -c 100 /dev/zero > $f; break; done
run $S; sed 's/^/    /' err.txt; cmp -s <(grep delta_ri= out.txt) <(grep delta_ri= ref.txt) && echo "  identical to the undamaged run"
run cache verify --cache c
mkdir keep; echo mine > keep/notes.txt
echo "## --overwrite on a folder twray did not write"; run generate --size-um 10,10,10 --out keep --overwrite; ls keep
echo "## absurd sizes"
for l in "rays: 1000000000000" "beam_um: 1000000000" "voxel_um: 0.000001"; do sed "/^${l%%:*}:/d" s.yaml > big.yaml; echo "$l" >> big.yaml; /usr/bin/time -f "  %e s" "$TW" study big.yaml --cache c2 --results r2 --dry-run 2>&1 | tail -2 | cut -c1-220; done
ls c2 r2 2>&1 | head -2
run generate --size-um 10000000,150,100 --out tenm.zarr
run trace --preset birch --thickness-mm 0.05 --delta-ri 0.01 --rays 1000000000000
run trace --preset birch --thickness-mm 0.05 --delta-ri 0.01 --beam-um 1e9
run generate --size-um 2000,2000,2000 --out cube.zarr --lazy
echo "## relative --cache with a scheduler whose workers run elsewhere: tests/test_study.py::test_relative_cache_and_results_are_the_clients_on_a_scheduler_whose_workers_live_elsewhere"
echo "## one-line errors"
printf '\x00\x01\xff\xfe' > bin.yaml; run study bin.yaml
run trace --preset birch --thickness-mm 0.05 --delta-ri 0.01 --out ""
touch afile; run trace --preset birch --thickness-mm 0.05 --delta-ri 0.01 --out afile/r.nc
/usr/bin/time -f "  %e s" "$TW" study s.yaml --scheduler tcp://127.0.0.1:9 --cache c3 --results r3 2>&1 | tail -2 | cut -c1-200
"$PY" -c "import numpy as np; np.save('v.npy', np.zeros((20,20,20),np.uint8)); np.save('e.npy', np.zeros((20,0,20),np.uint8))"
run trace --volume v.npy --delta-ri 0.01 --beam-um 100
run trace --volume e.npy --delta-ri 0.01 --beam-um 2
run trace --volume v.npy --delta-ri 0.01 --beam-um 5
echo "## Ctrl-C (SIGINT) during a 1 mm cube generate"
"$PY" - "$TW" <<'P'
import signal, subprocess, sys, time, pathlib
p = subprocess.Popen([sys.argv[1], "generate", "--size-um", "1000,1000,1000", "--out", "g.zarr", "--yes"],
                     stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
                     preexec_fn=lambda: signal.signal(signal.SIGINT, signal.SIG_DFL))  # as in a foreground shell
time.sleep(5); p.send_signal(signal.SIGINT); _, err = p.communicate()
print(f"  exit {p.returncode}; stderr: {err.strip().splitlines()[-1]}; {len(err.strip().splitlines())} lines")
print("  left:", [q.name for q in pathlib.Path(".").iterdir() if q.name.startswith(".g.zarr") or q.name == "g.zarr"])
P
echo "## concurrent: two studies on one cache and results folder"
rm -rf c r; ("$TW" $S > o1.txt 2> e1.txt; echo "  run 1 exit $?") & ("$TW" $S > o2.txt 2> e2.txt; echo "  run 2 exit $?") & wait
cmp -s <(grep delta_ri= o1.txt) <(grep delta_ri= ref.txt) && cmp -s <(grep delta_ri= o2.txt) <(grep delta_ri= ref.txt) && echo "  both identical to the undamaged run"
echo "## leftovers of an interrupted dataset write"
mkdir r/.faults.zarr.partial-deadbeefhost-1-0123abcd; touch -d '2 days ago' r/.faults.zarr.partial-deadbeefhost-1-0123abcd
run $S; ls -a r
echo "## a full disk at each stage (TWRAY_FAULT_ENOSPC=<stage>:0 fails that stage's writes as ENOSPC), then a rerun"
for stage in micro rays summary pool dataset; do
  rm -rf c r; TWRAY_FAULT_ENOSPC=$stage:0 "$TW" $S > out.txt 2> err.txt; rc=$?
  echo "  $stage: exit $rc; $(grep -vc '^twray study: ' err.txt) line(s): $(grep -v '^twray study: ' err.txt | cut -c1-230)"
  run $S; cmp -s <(grep delta_ri= out.txt) <(grep delta_ri= ref.txt) && echo "  rerun identical to the undamaged run"
done
echo "## a worker over its memory limit (each task first holds 1.5 GB; --memory-limit 1GB)"
rm -rf c r; TWRAY_FAULT_MEMORY_MB=1500 "$TW" $S --memory-limit 1GB > out.txt 2> err.txt; echo "  exit $?: $(grep -v '^twray study: ' err.txt | cut -c1-260)"
echo "  the log: $(grep -c 'memory' c/logs/*.log) lines about memory in $(ls c/logs)"
run $S; cmp -s <(grep delta_ri= out.txt) <(grep delta_ri= ref.txt) && echo "  rerun identical to the undamaged run"
