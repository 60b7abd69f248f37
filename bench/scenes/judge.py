"""A render judge for animated scenes: lodserver's levels beside gltfpack's, in motion.

    python bench/scenes/judge.py [--assets Fox,RiggedSimple,...] [--ratios 0.5,0.2]
                                 [--times 5] [--size 256] [--out bench/out/scenes/judge]

For every asset (the shared sample scenes Fox, RiggedSimple, AnimatedMorphCube
and BoxAnimated; the Fox subdivided on a flat grid to ~10k, ~40k and ~100k
triangles and Loop-subdivided to 9k and 37k by ``subdivide.py``, made first
when missing):

1. ``lodserver export IN.glb -o OUT.glb --separate --lods 1,R1,R2,...`` once
   (wall time of the command, and the build time lodserver prints), then for
   each ratio ``gltfpack -i IN.glb -o OUT.glb -si r -noq -af 0 [-se 1]``
   (npm ``gltfpack`` 1.3, WASM, installed in bench/scenes), one call per ratio
   (up to three tries, see :func:`gltfpack`). gltfpack's ratio r is chosen so
   that both have the same triangle count: lodserver's count when lodserver
   simplified the scene (else R times the input's). ``-se 1`` lifts
   gltfpack's 1% error limit when that stops it short of the count; ``-noq``
   and ``-af 0`` keep positions and animations unquantised and unresampled,
   so the renders differ by the simplification alone.
2. In headless Chromium (SwiftShader) ``judge.html`` loads the input and each
   candidate with three.js's GLTFLoader, plays every clip with an
   AnimationMixer at ``--times`` evenly spaced times ((k + 0.5) / times of its
   duration), and draws each pose with MeshNormalMaterial (flat shaded when a
   mesh has no normals, as glTF prescribes) from three views framed on the
   input's rest-pose bounding sphere, the same cameras for every candidate.
   Against the input at the same clip, time and view it measures the RMS of
   the normal image over the pixels both cover ([0, 1] colour units; 0.1 is
   a normal off by about 11 degrees) and the silhouette mismatch, pixels
   covered by one of the two over pixels covered by either.

Writes ``bench/scenes/results.md`` (the table: mean and worst over times and
views), ``results.json`` beside the candidates in ``--out`` (every frame's
figures too), and a PNG strip for each of the ``--shots`` assets in
``bench/scenes/shots/`` (input, then each candidate, at the middle time of the
first clip, first view).
"""

from __future__ import annotations

import argparse
import base64
import contextlib
import json
import os
import re
import shutil
import statistics
import subprocess
import sys
import time
from pathlib import Path

HERE = Path(__file__).resolve().parent
ROOT = HERE.parents[1]
sys.path.insert(0, str(HERE))
sys.path.insert(0, str(HERE.parent))  # bench/, for static_server.py
from glb import read_glb, triangle_count  # noqa: E402
from static_server import serve  # noqa: E402

SCENES = ROOT.parent / "shared" / "meshes" / "scenes"
SUBDIVIDED = ROOT / "bench" / "out" / "scenes"
ASSETS = {"Fox": SCENES / "Fox.glb", "RiggedSimple": SCENES / "RiggedSimple.glb",
          "AnimatedMorphCube": SCENES / "AnimatedMorphCube.glb",
          "BoxAnimated": SCENES / "BoxAnimated.glb",
          "Fox_10k": SUBDIVIDED / "Fox_10k.glb", "Fox_40k": SUBDIVIDED / "Fox_40k.glb",
          "Fox_100k": SUBDIVIDED / "Fox_100k.glb",
          "Fox_loop2": SUBDIVIDED / "Fox_loop2.glb", "Fox_loop3": SUBDIVIDED / "Fox_loop3.glb"}
GLTFPACK = HERE / "node_modules" / ".bin" / "gltfpack"
CHROMIUM = "/usr/bin/chromium"
CHROMIUM_ARGS = ["--headless", "--no-sandbox", "--disable-gpu", "--disable-quic", "--no-first-run",
                 "--disable-background-networking", "--disable-component-update",
                 "--disable-sync", "--use-angle=swiftshader", "--enable-unsafe-swiftshader"]
# directions from the centre towards the camera (all assets are Y-up):
# front-right and a little above, behind-left, and from above
VIEWS = [(0.8, 0.35, 1.0), (-1.0, 0.2, -0.6), (0.25, 1.0, 0.35)]
MATCH = 0.02  # gltfpack's count within 2% of the target, else one retry


def run(command: list[str], timeout: float) -> tuple[float, str]:
    """(wall seconds, stdout+stderr) of a command; a failure raises with its tail."""
    started = time.perf_counter()
    done = subprocess.run(command, capture_output=True, text=True, timeout=timeout, check=False)
    seconds = time.perf_counter() - started
    output = done.stdout + done.stderr
    if done.returncode != 0:
        raise RuntimeError(f"{command[0]} exited {done.returncode}: {output.strip()[-300:]}")
    return seconds, output


def triangles(path: Path) -> int:
    return triangle_count(read_glb(path)[0])


def lodserver_export(source: Path, folder: Path, ratios: list[float], timeout: float) -> dict:
    """One ``lodserver export --separate`` for every ratio; its levels' paths and counts."""
    out = folder / "lodserver.glb"
    lods = ",".join(f"{r:g}" for r in [1.0, *ratios])
    seconds, output = run([sys.executable, "-m", "lodserver.cli", "export", str(source), "-o",
                           str(out), "--separate", "--lods", lods], timeout)
    build = re.search(r"in ([0-9.]+) s", output)
    levels = {}
    for i, ratio in enumerate(ratios, start=1):
        path = folder / f"lodserver_lod{i}.glb"
        levels[ratio] = {"path": path, "triangles": triangles(path)}
    return {"seconds": seconds, "build_seconds": float(build.group(1)) if build else None,
            "message": output.strip().splitlines()[-1] if output.strip() else "",
            "levels": levels}


def gltfpack(source: Path, out: Path, target: int, base: int, timeout: float) -> dict:
    """gltfpack's output nearest ``target`` triangles of ``base``.

    First at ratio target/base with gltfpack's default error limit (1%); when
    that stops more than 2% above the target, again with the limit lifted
    (``-se 1``), and once more with the ratio scaled by target/got if that
    lands more than 2% off. Of the runs, the one nearest the target that kept
    any triangle is kept (with ``-se 1`` gltfpack may drop a mesh of
    disconnected flat faces entirely: BoxAnimated, AnimatedMorphCube)."""
    runs = []

    def attempt(ratio: float, limit: str | None):
        path = out.with_name(f"{out.stem}_{len(runs)}.glb")
        command = [str(GLTFPACK), "-i", str(source), "-o", str(path), "-si", f"{ratio:.6f}",
                   "-noq", "-af", "0"] + (["-se", limit] if limit else [])
        seconds, _ = run(command, timeout)
        runs.append({"path": path, "triangles": triangles(path), "ratio": ratio,
                     "error_limit": limit or "default", "seconds": seconds})
        return runs[-1]["triangles"]

    off = lambda got: abs(got - target) > MATCH * target
    ratio = min(1.0, target / base)
    got = attempt(ratio, None)
    if off(got) and got > target:
        got = attempt(ratio, "1")
        if off(got) and got > 0:
            attempt(min(1.0, ratio * target / got), "1")
    kept = [r for r in runs if r["triangles"] > 0] or runs
    best = min(kept, key=lambda r: abs(r["triangles"] - target))
    shutil.copyfile(best["path"], out)
    for r in runs:
        r["path"].unlink()
    best["path"], best["attempts"] = out, [
        {k: v for k, v in r.items() if k != "path"} for r in runs]
    return best


def attribute_names(path: Path) -> set[str]:
    """Every vertex attribute name of every primitive, and TARGET for morph targets."""
    document, _ = read_glb(path)
    names = set()
    for mesh in document.get("meshes", []):
        for p in mesh["primitives"]:
            names.update(p["attributes"])
            names.update(f"TARGET_{n}" for t in p.get("targets", []) for n in t)
    return names


def validator_errors(paths: list[Path]) -> list[int]:
    """The Khronos validator's error count per GLB (subdivide.validate)."""
    from subdivide import validate

    return [report["issues"]["numErrors"] for report in validate(paths)]


def candidates_for(key: str, source: Path, folder: Path, ratios: list[float], timeout: float):
    """The asset's candidates: [(name, path, info)] and the export record."""
    folder.mkdir(parents=True, exist_ok=True)
    # the page reads every file from the served repository, inputs included
    shutil.copyfile(source, folder / "input.glb")
    base = triangles(source)
    ours = lodserver_export(source, folder, ratios, timeout)
    record = {"asset": key, "triangles": base, "lodserver": ours, "ratios": {}}
    candidates = []
    for ratio in ratios:
        level = ours["levels"][ratio]
        simplified = level["triangles"] < 0.98 * base
        target = level["triangles"] if simplified else max(1, round(ratio * base))
        theirs = gltfpack(source, folder / f"gltfpack_{ratio:g}.glb", target, base, timeout)
        record["ratios"][ratio] = {"ours": level["triangles"], "theirs": theirs["triangles"],
                                   "target": target, "ours_simplified": simplified,
                                   "gltfpack_ratio": theirs["ratio"],
                                   "gltfpack_error_limit": theirs["error_limit"],
                                   "gltfpack_attempts": theirs["attempts"],
                                   "gltfpack_seconds": theirs["seconds"]}
        candidates.append((f"lodserver {ratio:g}", level["path"]))
        candidates.append((f"gltfpack {ratio:g}", theirs["path"]))
    # every candidate valid glTF, and which of the input's attributes it lost
    errors = validator_errors([path for _, path in candidates])
    names = attribute_names(source)
    for (name, path), count in zip(candidates, errors):
        record.setdefault("checks", {})[name] = {
            "validator_errors": count, "lost": sorted(names - attribute_names(path))}
    return candidates, record


def summary(rows: list[dict]) -> dict:
    """Mean and worst RMS and silhouette mismatch over a candidate's frames."""
    rms = [r["rms"] for r in rows if r["rms"] is not None]
    sil = [r["silhouette"] for r in rows]
    worst = max(rows, key=lambda r: r["silhouette"])
    return {"rms_mean": statistics.fmean(rms) if rms else None,
            "rms_worst": max(rms) if rms else None,
            "silhouette_mean": statistics.fmean(sil), "silhouette_worst": max(sil),
            "worst_at": f"{worst['clip']} t={worst['time']:.2f} view {worst['view']}",
            "frames": len(rows)}


def judge(assets: dict, ratios, times: int, size: int, out: Path, timeout: float,
          page_timeout: float, shots=()) -> list[dict]:
    """Export, render and compare every asset; one record per asset (a PNG
    strip in bench/scenes/shots/ for the assets named in ``shots``)."""
    from playwright.sync_api import Error as PlaywrightError
    from playwright.sync_api import sync_playwright

    prepared, records = [], []
    for key, source in assets.items():
        started = time.perf_counter()
        try:
            candidates, record = candidates_for(key, source, out / key, ratios, timeout)
        except (RuntimeError, subprocess.TimeoutExpired, OSError) as exc:
            # one asset's failed export is a row of the table, not the end of the run
            print(f"{key}: export failed: {exc}", file=sys.stderr, flush=True)
            records.append({"asset": key, "error": str(exc).strip().splitlines()[-1][:200]})
            continue
        prepared.append((key, source, candidates, record))
        print(f"{key}: exported in {time.perf_counter() - started:.1f} s "
              f"({record['lodserver']['message'][:160]})", file=sys.stderr, flush=True)
    with serve(ROOT) as base, sync_playwright() as playwright:
        browser = playwright.chromium.launch(executable_path=CHROMIUM, args=CHROMIUM_ARGS)
        try:
            page = browser.new_page(viewport={"width": 400, "height": 400})
            messages = []
            page.on("console", lambda m: messages.append(f"{m.type}: {m.text}"))
            page.on("pageerror", lambda e: messages.append(f"pageerror: {e}"))
            page.goto(f"{base}/bench/scenes/judge.html")
            page.wait_for_function("window.judgeReady === true", timeout=page_timeout * 1000)
            page.set_default_timeout(page_timeout * 1000)
            for key, source, candidates, record in prepared:
                url = lambda p: "/" + Path(p).resolve().relative_to(ROOT).as_posix()
                spec = {"input": url(out / key / "input.glb"), "views": VIEWS, "times": times, "size": size,
                        "margin": 1.05, "shot_frame": times // 2, "shot": key in shots,
                        "shot_size": 240,
                        "candidates": [{"name": n, "url": url(p)} for n, p in candidates]}
                started = time.perf_counter()
                try:
                    result = page.evaluate("(spec) => window.judge(spec)", spec)
                except PlaywrightError as exc:
                    raise RuntimeError(f"{key}: the page failed: {exc}\n{messages[-5:]}") from None
                shot = result.pop("shot")
                if shot:
                    (HERE / "shots").mkdir(exist_ok=True)
                    (HERE / "shots" / f"{key}.png").write_bytes(
                        base64.b64decode(shot.split(",", 1)[1]))
                record["render"] = {k: v for k, v in result.items() if k != "results"}
                record["candidates"] = {}
                for item in result["results"]:
                    if "error" in item:
                        record["candidates"][item["name"]] = {"error": item["error"]}
                    else:
                        record["candidates"][item["name"]] = {
                            "flat_meshes": item["flat"], **summary(item["rows"]),
                            "rows": item["rows"]}  # per clip, time and view, for results.json
                motion = result["input_motion"]
                print(f"{key}: judged {result['frames']} frames x {result['views']} views in "
                      f"{time.perf_counter() - started:.1f} s; the input's silhouette changes by "
                      f"{statistics.fmean(motion) if motion else 0:.3f} between frames",
                      file=sys.stderr, flush=True)
                records.append(record)
        finally:
            browser.close()
    return records


def fmt(value, digits=3):
    return "—" if value is None else f"{value:.{digits}f}"


def check(record: dict, method: str, ratio: float) -> str:
    c = record.get("checks", {}).get(f"{method} {ratio:g}")
    if c is None:
        return "—"
    return f"{c['validator_errors']}; " + (" ".join(c["lost"]) or "none")


def table(records: list[dict]) -> str:
    """The results as Markdown."""
    lines = [("| asset | ratio | triangles: input → lodserver / gltfpack | normal RMS mean (worst): "
              "lodserver / gltfpack | silhouette mismatch mean (worst): lodserver / gltfpack | "
              "export s: lodserver (both levels) / gltfpack (this level) | validator errors; "
              "attributes lost: lodserver / gltfpack |"),
             "|---|---|---|---|---|---|---|"]
    for rec in records:
        if "error" in rec:
            lines.append(f"| {rec['asset']} | — | export failed: {rec['error']} | | | | |")
            continue
        ours_s = rec["lodserver"]["seconds"]
        build = rec["lodserver"]["build_seconds"]
        for ratio, r in rec["ratios"].items():
            a = rec["candidates"].get(f"lodserver {ratio:g}", {})
            b = rec["candidates"].get(f"gltfpack {ratio:g}", {})
            cell = lambda c, k: c.get("error", "")[:40] or fmt(c.get(k + "_mean")) + (
                f" ({fmt(c.get(k + '_worst'))})")
            note = "" if r["ours_simplified"] else " (lodserver kept it whole)"
            if abs(r["ours"] - r["theirs"]) > MATCH * max(r["ours"], 1):
                note += " (**counts differ**)"
            if r["gltfpack_error_limit"] != "default":
                note += f" (gltfpack -se {r['gltfpack_error_limit']})"
            lines.append(
                f"| {rec['asset']} | {ratio:g} | {rec['triangles']:,} → {r['ours']:,} / "
                f"{r['theirs']:,}{note} | {cell(a, 'rms')} / {cell(b, 'rms')} | "
                f"{cell(a, 'silhouette')} / {cell(b, 'silhouette')} | {ours_s:.2f}"
                f"{f' (build {build:.2f})' if build is not None else ''} / "
                f"{r['gltfpack_seconds']:.2f} | {check(rec, 'lodserver', ratio)} / "
                f"{check(rec, 'gltfpack', ratio)} |")
    return "\n".join(lines)


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--assets", default=",".join(ASSETS), help="comma-separated names")
    parser.add_argument("--ratios", default="0.5,0.2")
    parser.add_argument("--times", type=int, default=5, help="times per clip")
    parser.add_argument("--size", type=int, default=320, help="render size in pixels")
    parser.add_argument("--out", type=Path, default=ROOT / "bench" / "out" / "scenes" / "judge")
    parser.add_argument("--shots", default="Fox,RiggedSimple,AnimatedMorphCube,Fox_loop3",
                        help="assets with a PNG strip in bench/scenes/shots/")
    parser.add_argument("--results", type=Path, default=HERE / "results.md")
    parser.add_argument("--timeout", type=float, default=300, help="seconds per export command")
    parser.add_argument("--page-timeout", type=float, default=300, help="seconds per asset's renders")
    args = parser.parse_args(argv)
    if not GLTFPACK.exists():
        print("gltfpack is not installed: run `npm i gltfpack gltf-validator` in bench/scenes",
              file=sys.stderr)
        return 2
    keys = [k for k in args.assets.split(",") if k]
    unknown = [k for k in keys if k not in ASSETS]
    if unknown:
        print(f"unknown assets {unknown}; known: {', '.join(ASSETS)}", file=sys.stderr)
        return 2
    if any(not ASSETS[k].exists() and k.startswith("Fox_") for k in keys):
        subprocess.run([sys.executable, str(HERE / "subdivide.py")], check=True)
    ratios = [float(r) for r in args.ratios.split(",") if r]
    # one untimed export first, so that compiling or loading numba's cached
    # kernels is not counted in the first asset's export time
    with contextlib.suppress(RuntimeError, subprocess.TimeoutExpired):
        warm = args.out / "warm-up"
        warm.mkdir(parents=True, exist_ok=True)
        run([sys.executable, "-m", "lodserver.cli", "export", str(ASSETS["RiggedSimple"]), "-o",
             str(warm / "w.glb"), "--separate", "--lods", "1,0.5"], args.timeout)
    started = time.perf_counter()
    records = judge({k: ASSETS[k] for k in keys}, ratios, args.times, args.size, args.out,
                    args.timeout, args.page_timeout, set(args.shots.split(",")))
    args.out.mkdir(parents=True, exist_ok=True)
    (args.out / "results.json").write_text(json.dumps(records, indent=1, default=str))
    commit = subprocess.run(["git", "-C", str(ROOT), "log", "-1", "--format=%h %s"],
                            capture_output=True, text=True, check=False).stdout.strip()[:80]
    dirty = subprocess.run(["git", "-C", str(ROOT), "status", "--short", "lodserver"],
                           capture_output=True, text=True, check=False).stdout.splitlines()
    if dirty:
        commit += f"` plus {len(dirty)} uncommitted files under lodserver/ (`git status`)"
    else:
        commit += "`"
    text = (f"# Scene judge results\n\n`python bench/scenes/judge.py` at `{commit}, "
            f"{time.strftime('%Y-%m-%d %H:%M UTC', time.gmtime())}, {os.cpu_count()} cores, "
            f"{args.times} times per clip x {len(VIEWS)} views at {args.size} px, "
            f"lodserver export `--lods 1,{args.ratios}`, "
            f"{time.perf_counter() - started:.0f} s in all.\n\n{table(records)}\n")
    args.results.write_text(text)
    print(text)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
