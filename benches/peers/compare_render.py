"""The table benches/peers/render.sh prints: for each case and step `defvol bench render`
timed (point-sampled and pre-integrated, unshaded), VTK's fixed-point caster on the same
exported work, both PSNRs against the same f64 reference, and VTK's time over defvol's.

usage: compare_render.py WORK_DIR PEER_PYTHON THREADS RUNS
"""

import json
import os
import subprocess
import sys


def main():
    work, python, threads, runs = sys.argv[1:5]
    rows = [json.loads(line) for line in open(os.path.join(work, "defvol.jsonl"))]
    rows = [r for r in rows if r["backend"] == "cpu" and r["params"]["shading"] == "none"]
    script = os.path.join(os.path.dirname(os.path.abspath(__file__)), "vtk_render.py")
    print(f'{"case":<14} {"step mm":>7} {"sampling":<15} {"defvol ms":>10} {"dB":>6} {"vtk ms":>8} {"dB":>6} '
          f'{"vtk/defvol":>10}')
    for case in sorted({r["case"] for r in rows}):
        # VTK logs to stderr on a machine without a display; its result is the JSON lines.
        out = subprocess.run([python, script, os.path.join(work, case), threads, runs], check=True,
                             capture_output=True, text=True)
        peers = [json.loads(line) for line in out.stdout.splitlines() if line.startswith("{")]
        for row in (r for r in rows if r["case"] == case):
            step = row["params"]["step_mm"]
            peer = next(p for p in peers if abs(p["step_mm"] - step) < 1e-9)
            a, t = row["time_ms"]["median"], peer["time_ms"]["median"]
            sampling = "pre-integrated" if row["params"]["preintegrated"] else "point"
            print(f'{case:<14} {step:7.2f} {sampling:<15} {a:10.1f} {row["error"]["value"]:6.1f} {t:8.1f} '
                  f'{peer["error"]["value"]:6.1f} {t / a:9.2f}x')
            print(json.dumps({"stage": "render", "case": case, "step_mm": step, "threads": int(threads),
                              "defvol": row, "vtk": peer, "ratio_vtk": t / a}), file=sys.stderr)


if __name__ == "__main__":
    main()
