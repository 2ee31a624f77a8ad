"""The table benches/peers/run.sh prints: for each case `defvol bench warp` timed, Taichi's
kernel on the same exported work, and the ratio.

usage: compare.py WORK_DIR PEER_PYTHON THREADS RUNS
"""

import json
import os
import subprocess
import sys


def main():
    work, python, threads, runs = sys.argv[1:5]
    rows = [json.loads(line) for line in open(os.path.join(work, "defvol.jsonl"))]
    rows = [r for r in rows if r["backend"] == "cpu"]
    script = os.path.join(os.path.dirname(os.path.abspath(__file__)), "taichi_warp.py")
    print(f'{"case":<22} {"defvol ms":>10} {"taichi ms":>10} {"vs taichi":>10} {"defvol err":>11} {"taichi err":>11}')
    for fast in rows:
        case_dir = os.path.join(work, f'{fast["case"]}_{fast["params"]["sampling"]}')
        # The last line: Taichi prints its banner on import.
        out = subprocess.run([python, script, case_dir, threads, runs], check=True, capture_output=True, text=True)
        peer = json.loads(out.stdout.strip().splitlines()[-1])
        a, t = fast["time_ms"]["median"], peer["time_ms"]["median"]
        print(f'{fast["case"]:<22} {a:10.2f} {t:10.2f} {t / a:9.1f}x '
              f'{fast["error"]["value"]:11.2e} {peer["error"]["value"]:11.2e}')
        print(json.dumps({"stage": "warp", "case": fast["case"], "threads": int(threads), "defvol": fast,
                          "taichi": peer, "ratio_taichi": t / a}), file=sys.stderr)


if __name__ == "__main__":
    main()
