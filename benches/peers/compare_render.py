"""The table benches/peers/render.sh prints: for each case and step `defvol bench render`
timed (point-sampled and pre-integrated, unshaded), VTK's fixed-point caster on the same
exported work, both PSNRs against the same f64 reference, and VTK's time over defvol's.
The two took turns for ROUNDS rounds: a round's ratio is its two medians' (both measured
while the host was in one state), and the table gives the median and the range of them.
A second table compares at equal accuracy, as the field compares renderers: for each step
VTK ran, defvol's fastest step and sampling (of those run) whose PSNR is at least VTK's.

usage: compare_render.py WORK_DIR ROUNDS THREADS
   WORK_DIR holds defvol-R.jsonl (`defvol bench render --json`) and vtk-R.jsonl
   (vtk_render.py's lines) for R = 1..ROUNDS
"""

import json
import os
import statistics
import sys


def read(path):
    return [json.loads(line) for line in open(path) if line.startswith("{")]


def main():
    work, rounds, threads = sys.argv[1], int(sys.argv[2]), int(sys.argv[3])
    # (case, step, pre-integrated) -> one (defvol row, VTK row) a round.
    pairs = {}
    for r in range(1, rounds + 1):
        peers = read(os.path.join(work, f"vtk-{r}.jsonl"))
        for row in read(os.path.join(work, f"defvol-{r}.jsonl")):
            if row["backend"] != "cpu" or row["params"]["shading"] != "none":
                continue
            case, step = row["case"], row["params"]["step_mm"]
            peer = next(p for p in peers if p["case"] == case and abs(p["step_mm"] - step) < 1e-9)
            pairs.setdefault((case, step, row["params"]["preintegrated"]), []).append((row, peer))
    print(f'{"case":<14} {"step mm":>7} {"sampling":<15} {"defvol ms":>10} {"dB":>6} {"vtk ms":>8} {"dB":>6} '
          f'{"vtk/defvol":>10} {"per round":>13}')
    for (case, step, preintegrated), runs in sorted(pairs.items()):
        ours = [row["time_ms"]["median"] for row, _ in runs]
        theirs = [peer["time_ms"]["median"] for _, peer in runs]
        ratios = [t / a for a, t in zip(ours, theirs)]
        sampling = "pre-integrated" if preintegrated else "point"
        row, peer = runs[-1]
        print(f'{case:<14} {step:7.2f} {sampling:<15} {statistics.median(ours):10.1f} {row["error"]["value"]:6.1f} '
              f'{statistics.median(theirs):8.1f} {peer["error"]["value"]:6.1f} {statistics.median(ratios):9.2f}x '
              f'{min(ratios):6.2f}-{max(ratios):.2f}x')
        print(json.dumps({"stage": "render", "case": case, "step_mm": step, "threads": threads,
                          "defvol": [r for r, _ in runs], "vtk": [p for _, p in runs],
                          "ratio_vtk": statistics.median(ratios), "ratios_vtk": ratios}), file=sys.stderr)
    at_equal_accuracy(pairs, threads)


def median(rows):
    """The median of the rows' medians (one a round)."""
    return statistics.median(row["time_ms"]["median"] for row in rows)


def at_equal_accuracy(pairs, threads):
    """For each case and step VTK ran: defvol's fastest run (any step and sampling) whose
    PSNR is at least VTK's there, both timed in the same rounds."""
    print("\nat equal accuracy (defvol's fastest run at VTK's PSNR or above)")
    print(f'{"case":<14} {"vtk step":>8} {"vtk ms":>8} {"dB":>6} {"step mm":>7} {"sampling":<15} '
          f'{"defvol ms":>10} {"dB":>6} {"vtk/defvol":>10} {"per round":>13}')
    vtk_runs = {(case, step): [peer for _, peer in runs] for (case, step, _), runs in pairs.items()}
    for (case, step), peers in sorted(vtk_runs.items()):
        floor = peers[-1]["error"]["value"]
        closer = [(key, [row for row, _ in runs]) for key, runs in pairs.items()
                  if key[0] == case and runs[-1][0]["error"]["value"] >= floor]
        if not closer:
            print(f'{case:<14} {step:8.2f} no defvol run reached {floor:.1f} dB')
            continue
        (_, ours_step, preintegrated), rows = min(closer, key=lambda c: median(c[1]))
        ratios = [peer["time_ms"]["median"] / row["time_ms"]["median"] for row, peer in zip(rows, peers)]
        sampling = "pre-integrated" if preintegrated else "point"
        theirs = median(peers)
        print(f'{case:<14} {step:8.2f} {theirs:8.1f} {floor:6.1f} {ours_step:7.2f} {sampling:<15} '
              f'{median(rows):10.1f} {rows[-1]["error"]["value"]:6.1f} {statistics.median(ratios):9.2f}x '
              f'{min(ratios):6.2f}-{max(ratios):.2f}x')
        print(json.dumps({"stage": "render", "comparison": "equal_accuracy", "case": case, "vtk_step_mm": step,
                          "defvol_step_mm": ours_step, "preintegrated": preintegrated, "threads": threads,
                          "ratio_vtk": statistics.median(ratios), "ratios_vtk": ratios}), file=sys.stderr)


if __name__ == "__main__":
    main()
