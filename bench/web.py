"""The web player: size of ``atgs-export --format web`` against the PLY export, and the page in
headless Chromium (software WebGL2 on this machine's CPUs: a floor, not a GPU figure) against
``atgs-view --headless`` of the same checkpoint, camera and frame.

    python bench/web.py --checkpoint runs/demo/ckpt.pt [--extra-checkpoint runs/n3dv/ckpt.pt]
    # writes bench/results/web.json and the table in README.md
    python bench/web.py --part memory [--memory-baseline ad35ea5]
    # the page's memory while a synthetic 1,200-frame export plays through twice (no checkpoint
    # needed): merged into bench/results/web.json under "memory", its other keys kept
    python bench/web.py --part bytes --checkpoint runs/demo/ckpt.pt [--scene PREPARED]
    # bytes a frame against held-out PSNR of both streams (bench/_web_bytes.py): the "bytes" key of
    # bench/results/web.json (the others kept) and the table in docs/web.md; with each seek's time
    # and, for the model stream, the page's decode and frame-preparation times. --bytes-routes a:
    # the model stream only (with --out elsewhere and --bytes-docs None --docs None: a comparison run)

Targets (issue 39): the web export at most 1/8 of the PLY export's bytes; the browser's frames at
least 35 dB against atgs-render; the first frame within 2 s of opening the page on localhost.
"""

from __future__ import annotations

import json
import os
import statistics
import tempfile
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Literal

import numpy as np
import torch
import tyro

# bench/_docs.py and bench/_web_bytes.py (the script's folder is on sys.path)
from _docs import REPO, publish, run_stamp, update_docs_table, write_json_atomic
from _web_bytes import bytes_curve, bytes_rows, bytes_table
from atgs.eval.metrics import psnr
from atgs.web.browser import PlayerPage, chromium, serving
from atgs.web.synthetic import synthetic_export

SIZE_TARGET = 1 / 8
PSNR_TARGET_DB = 35.0
FIRST_FRAME_TARGET_S = 2.0


@dataclass
class BenchConfig:
    part: Literal["all", "memory", "bytes"] = "all"
    """all: size, browser against atgs-view, first frame, playback of --checkpoint; memory: the page's
    memory over a long synthetic export; bytes: the bytes-a-frame against held-out PSNR curve of both
    web streams (memory and bytes are merged into --out, whose other keys stay)."""
    checkpoint: Path = Path("runs/demo/ckpt.pt")
    """The built-in scene's trained checkpoint (./scripts/demo.sh writes runs/demo/ckpt.pt)."""
    extra_checkpoints: list[Path] = field(default_factory=list)
    """More checkpoints whose web export size is reported (e.g. the real N3DV frame's model)."""
    extra_names: list[str] = field(default_factory=list)
    """What each of --extra-checkpoints is, for the table (default: its path)."""
    chunk_frames: int = 8
    views: int = 4
    """Frames (evenly spaced) compared on each of the held-out camera and one training camera."""
    loads: int = 3
    """Page loads timed to the first frame."""
    play_seconds: float = 8.0
    """Playback measured after the stream has loaded."""
    screenshot: Path | None = Path("docs/images/web_player.png")
    """The page at 1280x720 while playing (the README's picture); None: none."""
    replot: bool = False
    """Only rewrite the table from --out's results (no measurement)."""
    memory_frames: int = 1200
    memory_gaussians: int = 12000
    """The synthetic long export of --part memory: frames, and Gaussians a frame."""
    memory_budget_mb: float | None = None
    """The page's budget (URL parameter budget); None: the player's default."""
    memory_baseline: str | None = None
    """Also measure the player of this git commit (e.g. one before the budget) on the same export."""
    memory_speed: str = "2"
    """Playback speed (the page's speed menu) during the memory run."""
    memory_docs: Path | None = Path("docs/web.md")
    """The page with the bench:web-memory markers (the memory runs' table)."""
    scene: Path | None = None
    """--part bytes: the prepared scene of the held-out ground truth (default: the checkpoint's data_dir)."""
    bytes_frames: int = 6
    """--part bytes: frames (evenly spaced) of the held-out camera."""
    bytes_routes: tuple[str, ...] = ("a", "b")
    """--part bytes: the routes measured: "a" the model stream, "b" the Gaussian chunks."""
    bytes_docs: Path | None = Path("docs/web.md")
    """--part bytes: the page with the bench:web-bytes markers."""
    out: Path = Path("bench/results/web.json")
    docs: Path | None = Path("README.md")
    """The page with the bench:web markers (issue 39 asks for the figures in the README)."""


def _psnr(a: np.ndarray, b: np.ndarray) -> float:
    return float(psnr(torch.from_numpy(a).double(), torch.from_numpy(b).double()))


def _bytes(folder: Path) -> int:
    return sum(p.stat().st_size for p in folder.rglob("*") if p.is_file())


def _desktop(ckpt: Path, camera: int, frame: int, out: Path) -> np.ndarray:
    from atgs.io.images import read_rgb8
    from atgs.viewer.cli import main as view_main

    assert view_main([str(ckpt), "--headless", "--device", "cpu", "--camera", str(camera), "--frame", str(frame),
                      "--out", str(out)]) == 0
    return read_rgb8(out).astype(np.float32) / 255.0


def _export(ckpt: Path, out: Path, fmt: str, chunk_frames: int, extra: list[str] | None = None) -> float:
    from atgs.cli.export import main as export_main

    t0 = time.perf_counter()
    args = [str(ckpt), "--out", str(out), "--format", fmt, "--no-progress", *(extra or [])]
    if fmt == "web" and extra is None:
        args += ["--web-stream", "gaussians", "--chunk-frames", str(chunk_frames)]
    assert export_main(args) == 0
    return time.perf_counter() - t0


def _drawn_per_frame(stream: Path, man: dict) -> list[int]:
    """Gaussians present in each exported frame (opacity above 0 as stored; the reference reader)."""
    from atgs.web.stream_format import decode_chunk

    return [int((fr.opacities > 0).sum()) for c in man["chunks"]
            for fr in decode_chunk((stream / c["file"]).read_bytes()).frames]


def size_row(ckpt: Path, tmp: Path, chunk_frames: int, with_ply: bool) -> tuple[dict, Path]:
    """The web export's (and with ``with_ply`` the PLY export's) size; (row, the web folder)."""
    web = tmp / f"web-{len(list(tmp.glob('web-*')))}"
    web_s = _export(ckpt, web, "web", chunk_frames)
    man = json.loads((web / "stream" / "manifest.json").read_text())
    stream = sum(c["bytes"] for c in man["chunks"])
    frames = len(man["frames"])
    union = sum(c["gaussians"] * c["frames"] for c in man["chunks"])
    static = sum(c["static"] * c["frames"] for c in man["chunks"])
    drawn = _drawn_per_frame(web / "stream", man)
    row = {"checkpoint": str(ckpt), "step": man["source"].get("step"), "frames": frames,
           "chunks": len(man["chunks"]), "chunk_frames": chunk_frames,
           "export_s": web_s, "stream_bytes": stream, "folder_bytes": _bytes(web),
           "bytes_per_frame": stream / frames, "bytes_per_gaussian_frame": stream / sum(drawn),
           "gaussians_per_frame_mean": sum(drawn) / frames, "static_share": static / union}
    if with_ply:
        ply = tmp / f"ply-{web.name}"
        row["ply_export_s"] = _export(ckpt, ply, "ply", chunk_frames)
        row["ply_bytes"] = _bytes(ply)
        row["ratio_to_ply"] = row["folder_bytes"] / row["ply_bytes"]
    return row, web


def _views(man: dict, views: int) -> tuple[list[int], list[int], list[int]]:
    """(the first held-out camera and the first training camera, the held-out ones, ``views``
    evenly spaced exported frames)."""
    n = len(man["frames"])
    held = [i for i, c in enumerate(man["cameras"]) if c.get("held_out")]
    cams = (held[:1] or [0]) + [next(i for i, c in enumerate(man["cameras"]) if not c.get("held_out"))]
    return cams, held, sorted({round(k * (n - 1) / max(views - 1, 1)) for k in range(views)})


def compare_views(browser, url: str, ckpt: Path, man: dict, views: int, tmp: Path) -> list[dict]:
    """PSNR of the page's canvas against atgs-view --headless, per camera and frame."""
    cams, held, frames = _views(man, views)
    rows = []
    for cam in cams:
        page = PlayerPage(browser, url, {"camera": cam, "paused": 1, "size": "camera"})
        page.first_frame()
        for i in frames:
            page.seek(i)
            got = page.pixels()
            want = _desktop(ckpt, cam, man["frames"][i], tmp / f"d{cam}_{i}.png")
            rows.append({"camera": man["cameras"][cam]["name"], "held_out": cam in held,
                         "frame": man["frames"][i], "size": list(got.shape[1::-1]), "db": _psnr(got, want)})
        page.close()
    return rows


def browser_rows(ckpt: Path, web: Path, cfg: BenchConfig, tmp: Path) -> dict:
    man = json.loads((web / "stream" / "manifest.json").read_text())
    cams, _, _ = _views(man, cfg.views)
    out: dict = {"psnr": [], "first_frame_s": []}
    with chromium() as browser, serving(web) as url:
        out["psnr"] = compare_views(browser, url, ckpt, man, cfg.views, tmp)
        for _ in range(cfg.loads):
            page = PlayerPage(browser, url, {"camera": cams[0], "paused": 1, "size": "camera"})
            page.first_frame()
            out["first_frame_s"].append(page.state()["firstFrameMs"] / 1000)
            page.close()
        for size in ("camera", None):
            params = {"camera": cams[0]} | ({"size": size} if size else {})
            page = PlayerPage(browser, url, params)
            if size is None:
                page.page.set_viewport_size({"width": 1280, "height": 720})
            page.first_frame()
            # the look-ahead window full (the whole video, when it fits the budget)
            page.page.wait_for_function("() => window.atgsPlayer.state().windowFull", timeout=120_000)
            s0, t0 = page.state(), time.perf_counter()
            time.sleep(cfg.play_seconds)
            s1, t1 = page.state(), time.perf_counter()
            w, h = page.page.evaluate("() => { const c = document.querySelector('canvas'); "
                                      "return [c.width, c.height]; }")
            if size is None and cfg.screenshot is not None:
                page.page.screenshot(path=str(cfg.screenshot))
            out.setdefault("playback", []).append({
                "canvas": [w, h], "draws_per_s": (s1["framesDrawn"] - s0["framesDrawn"]) / (t1 - t0),
                "page_draw_fps": s1.get("drawFps"), "video_fps": man["fps"]})
            page.close()
    return out


def _memory_sample(page: PlayerPage, cdp, t0: float, collect: bool = False) -> dict:
    """One sample (with ``collect``, after a full garbage collection: what the page really holds):
    the V8 heap (Performance.getMetrics' JSHeapUsedSize, which leaves out the
    contents of ArrayBuffers), the ArrayBuffer contents (Runtime.getHeapUsage's
    backingStorageSize: where fetched and decoded chunks live) and what the page says it holds."""
    if collect:
        cdp.send("HeapProfiler.collectGarbage")
    metrics = {m["name"]: m["value"] for m in cdp.send("Performance.getMetrics")["metrics"]}
    usage = cdp.send("Runtime.getHeapUsage")
    s = page.state()
    return {"t_s": round(time.perf_counter() - t0, 2), "frame": s["frame"], "js_heap_used": metrics["JSHeapUsedSize"],
            "array_buffers": usage.get("backingStorageSize"), "held_bytes": s.get("heldBytes"),
            "held_chunks": s.get("heldChunks"), "fetched_bytes": s["loadedBytes"], "after_gc": collect}


def play_twice(browser, url: str, params: dict, speed: str, sample_s: float = 0.5, collect_every: int = 4,
               limit_s: float = 900.0) -> dict:
    """Play the page's video through twice from frame 0, sampling its memory every ``sample_s``,
    every ``collect_every``-th sample after a garbage collection. V8 collects ArrayBuffers in
    bursts, letting about 64 MiB of garbage pile up above what is live: the samples between
    collections show that garbage, the collected ones what the page holds."""
    page = PlayerPage(browser, url, params)
    cdp = page.page.context.new_cdp_session(page.page)
    cdp.send("Performance.enable")
    page.first_frame()
    page.page.select_option("#speed", speed)
    t0 = time.perf_counter()
    samples = [_memory_sample(page, cdp, t0)]
    # the page counts the passes itself (each frame back to an earlier one: the loop wrapped), at
    # every animation frame: samples far apart under load would miss a short video's wraps
    page.page.evaluate("() => { window.benchPasses = 0; let last = -1; const watch = () => { "
                       "const f = window.atgsPlayer.state().frame; if (f < last) window.benchPasses++; last = f; "
                       "requestAnimationFrame(watch); }; requestAnimationFrame(watch); }")
    page.call("p.play()")
    passes = 0
    while passes < 2 and time.perf_counter() - t0 < limit_s:
        time.sleep(sample_s)
        samples.append(_memory_sample(page, cdp, t0, collect=len(samples) % collect_every == 0))
        passes = page.page.evaluate("() => window.benchPasses")
        samples[-1]["pass"] = passes
    page.call("p.pause()")
    after_gc = _memory_sample(page, cdp, t0, collect=True)
    s = page.state()
    page.close()
    return {"samples": samples, "after_gc": after_gc, "passes": passes, "error": s["error"],
            "frames_drawn": s["framesDrawn"], "fetched_bytes": s["loadedBytes"], "downloads": s.get("downloads"),
            "peak_held_bytes": s.get("peakHeldBytes"), "peak_held_chunks": s.get("peakHeldChunks"),
            "budget_bytes": s.get("budgetBytes")}


def _old_player(folder: Path, commit: str) -> None:
    """Replace ``folder``'s player by atgs/web/player of git ``commit`` (a before/after comparison)."""
    import subprocess

    names = subprocess.run(["git", "ls-tree", "--name-only", commit, "atgs/web/player/"], capture_output=True,
                           text=True, check=True, cwd=REPO).stdout.split()
    assert names, f"no atgs/web/player at {commit}"
    for name in names:
        data = subprocess.run(["git", "show", f"{commit}:{name}"], capture_output=True, check=True, cwd=REPO).stdout
        base = Path(name).name
        (folder / (base if base == "index.html" else f"player/{base}")).write_bytes(data)


def _memory_summary(run: dict, total: int) -> dict:
    """Peaks per pass of the V8 heap, the ArrayBuffers and both, in bytes: over every sample
    ("pass1"), and over the samples taken after a garbage collection ("pass1_live")."""
    out = {}
    for k in (1, 2):
        for suffix, only_live in (("", False), ("_live", True)):
            rows = [r for r in run["samples"] if r.get("pass", 0) == k - 1 and (r["after_gc"] or not only_live)]
            if rows:
                peak = {key: max(r[key] or 0 for r in rows) for key in ("js_heap_used", "array_buffers")}
                peak["both"] = max(r["js_heap_used"] + (r["array_buffers"] or 0) for r in rows)
                out[f"pass{k}{suffix}"] = peak
    out["fetched_over_total"] = run["fetched_bytes"] / total
    live = [r["array_buffers"] or 0 for r in run["samples"] if r["after_gc"]]
    out["live_array_buffers_median"] = statistics.median(live) if live else None
    if "pass1_live" in out and "pass2_live" in out:
        # flat: what the page holds peaks no higher in the second pass than in the first (but 10%)
        out["flat"] = out["pass2_live"]["both"] <= 1.1 * out["pass1_live"]["both"]
        budget = run.get("budget_bytes")
        peak = max(out[p]["array_buffers"] for p in ("pass1_live", "pass2_live"))
        out["under_budget"] = None if budget is None else peak <= budget
        out["under_budget_median"] = None if budget is None else out["live_array_buffers_median"] <= budget
    return out


def memory_run(cfg: BenchConfig) -> dict:
    """The page's memory while a long synthetic export plays through twice (issue 50)."""
    with tempfile.TemporaryDirectory() as d:
        web = Path(d) / "long"
        t = time.perf_counter()
        man = synthetic_export(web, frames=cfg.memory_frames, gaussians=cfg.memory_gaussians,
                               chunk_frames=cfg.chunk_frames)
        export_s = time.perf_counter() - t
        total = sum(c["bytes"] for c in man["chunks"])
        params = {"camera": 0, "size": "camera", "paused": 1}
        if cfg.memory_budget_mb is not None:
            params["budget"] = cfg.memory_budget_mb
        runs = {}
        with chromium() as browser:
            with serving(web) as url:
                runs["this commit"] = play_twice(browser, url, params, cfg.memory_speed)
            if cfg.memory_baseline:
                _old_player(web, cfg.memory_baseline)
                with serving(web) as url:
                    runs[cfg.memory_baseline] = play_twice(browser, url, params, cfg.memory_speed)
    for r in runs.values():
        r["summary"] = _memory_summary(r, total)
    return {"export": {"frames": cfg.memory_frames, "gaussians": cfg.memory_gaussians, "chunk_frames": cfg.chunk_frames,
                       "chunks": len(man["chunks"]), "stream_bytes": total, "canvas": [man["cameras"][0]["width"],
                       man["cameras"][0]["height"]], "written_s": export_s, "speed": cfg.memory_speed},
            "runs": runs, "machine": {"cpus": os.cpu_count()}, **run_stamp()}


def run(cfg: BenchConfig) -> dict:
    load_before = os.getloadavg()
    with tempfile.TemporaryDirectory() as d:
        tmp = Path(d)
        main_row, web = size_row(cfg.checkpoint, tmp, cfg.chunk_frames, with_ply=True)
        pages = browser_rows(cfg.checkpoint, web, cfg, tmp)
        extra = []
        for i, ckpt in enumerate(cfg.extra_checkpoints):
            row, web = size_row(ckpt, tmp, cfg.chunk_frames, with_ply=False)
            row["name"] = cfg.extra_names[i] if i < len(cfg.extra_names) else str(ckpt)
            man = json.loads((web / "stream" / "manifest.json").read_text())
            with chromium() as browser, serving(web) as url:
                row["psnr"] = compare_views(browser, url, ckpt, man, 2, tmp)
            extra.append(row)
    psnrs = [p["db"] for p in pages["psnr"]]
    return {"size": main_row, "extra": extra, "browser": pages,
            "summary": {"ratio_to_ply": main_row["ratio_to_ply"], "psnr_min_db": min(psnrs),
                        "psnr_median_db": statistics.median(psnrs),
                        "first_frame_s_median": statistics.median(pages["first_frame_s"])},
            "machine": {"cpus": os.cpu_count(), "loadavg_before": list(load_before)}, **run_stamp()}


def markdown_table(r: dict) -> str:
    s, b, m = r["size"], r["browser"], r["summary"]
    ok = lambda good: "reached" if good else "not reached"  # noqa: E731
    rows = [
        f"Measured {r['date']} at {r['commit']} with `python bench/web.py --checkpoint {s['checkpoint']}` on "
        f"{r['machine']['cpus']} CPUs; Chromium with software WebGL2 (SwiftShader): browser figures are a floor.", "",
        "| what | measured | target |", "|---|---|---|",
        f"| web export of the built-in scene's model as Gaussian chunks (`--web-stream gaussians`, "
        f"{s['step']:,} steps) | {s['folder_bytes'] / 2**20:.1f} MiB "
        f"for {s['frames']} frames: "
        f"{s['bytes_per_frame'] / 1024:.0f} KiB a frame, {s['bytes_per_gaussian_frame']:.2f} B per Gaussian a frame "
        f"({s['gaussians_per_frame_mean']:,.0f} Gaussians a frame; {100 * s['static_share']:.0f}% of each chunk's "
        f"Gaussians unchanged over it, stored once) | |",
        f"| PLY export of the same frames | {s['ply_bytes'] / 2**20:.1f} MiB | |",
        f"| web / PLY bytes | 1/{1 / s['ratio_to_ply']:.1f} | at most 1/8: {ok(s['ratio_to_ply'] <= SIZE_TARGET)} |",
        f"| browser against atgs-view --headless, {len(b['psnr'])} views | min {m['psnr_min_db']:.1f} dB, "
        f"median {m['psnr_median_db']:.1f} dB | 35 dB: {ok(m['psnr_min_db'] >= PSNR_TARGET_DB)} |",
        f"| first frame after opening the page (localhost, {len(b['first_frame_s'])} loads) | median "
        f"{m['first_frame_s_median']:.2f} s (max {max(b['first_frame_s']):.2f} s) | 2 s: "
        f"{ok(max(b['first_frame_s']) <= FIRST_FRAME_TARGET_S)} |",
    ]
    for p in b["playback"]:
        rows.append(f"| playback, canvas {p['canvas'][0]}x{p['canvas'][1]} | {p['draws_per_s']:.1f} frames drawn a "
                    f"second (video at {p['video_fps']:g} fps) | a floor |")
    for e in r["extra"]:
        db = [p["db"] for p in e["psnr"]]
        rows.append(f"| web export of {e['name']} as Gaussian chunks ({e['step']:,} steps) | "
                    f"{e['bytes_per_gaussian_frame']:.2f} B per Gaussian a frame, {e['gaussians_per_frame_mean']:,.0f} "
                    f"Gaussians, {e['frames']} frame(s); browser against atgs-view {min(db):.1f}-{max(db):.1f} dB "
                    f"({len(db)} views at {e['psnr'][0]['size'][0]}x{e['psnr'][0]['size'][1]}) | |")
    rows += bytes_rows(r.get("bytes"))
    rows += memory_rows(r.get("memory"))
    return "\n".join(rows)


def memory_table(m: dict) -> str:
    """docs/web.md's table of the memory runs."""
    e = m["export"]
    head = [f"Synthetic export: {e['frames']} frames of {e['gaussians']:,} Gaussians, {e['chunks']} chunks of "
            f"{e['chunk_frames']} frames, {e['stream_bytes'] / 2**20:.1f} MiB; "
            f"canvas {e['canvas'][0]}x{e['canvas'][1]}, "
            f"speed {e['speed']}x; {m['machine']['cpus']} CPUs, Chromium with SwiftShader.", "",
            "| what | measured | target |", "|---|---|---|"]
    rows = []
    for name, r in m["runs"].items():
        if r.get("peak_held_bytes") is not None:
            rows.append(f"| the player of {name}: compressed chunks held (the page's count) | peak "
                        f"{r['peak_held_bytes'] / 2**20:.1f} MiB, {r['peak_held_chunks']} chunks; "
                        f"{r['downloads']} downloads for {e['chunks']} chunks over two passes | at most the budget |")
        rows.append(f"| the player of {name}: after the second pass and a garbage collection | JS heap "
                    f"{r['after_gc']['js_heap_used'] / 2**20:.1f} MiB, ArrayBuffers "
                    f"{(r['after_gc']['array_buffers'] or 0) / 2**20:.1f} MiB | |")
    return "\n".join(head + memory_rows(m) + rows)


def memory_rows(m: dict | None) -> list[str]:
    """The --part memory rows of the table (none before it ran)."""
    if not m:
        return []
    e = m["export"]
    mib = lambda b: f"{b / 2**20:.1f} MiB"  # noqa: E731
    rows = []
    for name, r in m["runs"].items():
        p1, p2 = r["summary"].get("pass1_live"), r["summary"].get("pass2_live")
        if not (p1 and p2):
            continue
        raw = max(r["summary"]["pass1"]["array_buffers"], r["summary"]["pass2"]["array_buffers"])
        summary = r["summary"]
        budget = f"budget {mib(r['budget_bytes'])}" if r.get("budget_bytes") else "no budget"
        ok = lambda good: "reached" if good else "not reached"  # noqa: E731
        verdict = f"flat: {ok(summary['flat'])}" + (
            "" if summary["under_budget"] is None else
            f"; under the budget: {ok(summary['under_budget_median'])} at the median, "
            f"{ok(summary['under_budget'])} at the peak")
        rows.append(
            f"| memory: the player of {name} ({budget}), a synthetic {e['frames']}-frame export "
            f"({mib(e['stream_bytes'])}) played through twice ({m['date']} at {m['commit']}) | held after garbage "
            f"collections, peaks of passes 1 / 2: JS heap {mib(p1['js_heap_used'])} / {mib(p2['js_heap_used'])}, "
            f"ArrayBuffers {mib(p1['array_buffers'])} / {mib(p2['array_buffers'])} (median "
            f"{mib(summary['live_array_buffers_median'])}; with the garbage between collections up to {mib(raw)}); "
            f"fetched {mib(r['fetched_bytes'])} | {verdict} |")
    return rows


def run_bytes(cfg: BenchConfig) -> None:
    """--part bytes: the curve, merged into --out (its other keys kept) and tabled in docs/web.md."""
    with tempfile.TemporaryDirectory() as d:
        curve = bytes_curve(cfg.checkpoint, cfg.scene, cfg.bytes_frames, Path(d),
                            lambda ckpt, out, extra: _export(ckpt, out, "web", cfg.chunk_frames, extra), _desktop,
                            _psnr, cfg.bytes_routes)
    curve.update(machine={"cpus": os.cpu_count()}, **run_stamp())
    result = json.loads(cfg.out.read_text()) if cfg.out.exists() else {}
    result["bytes"] = curve
    write_json_atomic(cfg.out, result)
    table = bytes_table(curve, f"{curve['date']} at {curve['commit']}")
    print(table)
    if "size" in result:  # the rest of the table measured before: the README's table again, with these rows
        publish(result, cfg.out, markdown_table(result), cfg.docs, "web")
    if cfg.bytes_docs is not None:
        update_docs_table(cfg.bytes_docs, "web-bytes", table)


def main(cfg: BenchConfig) -> None:
    previous = json.loads(cfg.out.read_text()) if cfg.out.is_file() else {}
    if cfg.part == "memory":
        if cfg.replot:  # the summaries again from the stored samples
            memory = previous["memory"]
            for r in memory["runs"].values():
                r["summary"] = _memory_summary(r, memory["export"]["stream_bytes"])
        else:
            memory = memory_run(cfg)
        result = {**previous, "memory": memory}
        whole = "size" in result  # the rest of the table measured before: the README's table again
        publish(result, cfg.out, markdown_table(result) if whole else memory_table(result["memory"]),
                cfg.docs if whole else None, "web")
        if cfg.memory_docs is not None:
            update_docs_table(cfg.memory_docs, "web-memory", memory_table(result["memory"]))
        return
    if cfg.part == "bytes":
        run_bytes(cfg)
        return
    if cfg.replot:
        result = json.loads(cfg.out.read_text())
        publish(result, cfg.out, markdown_table(result), cfg.docs, "web")
        return
    for c in [cfg.checkpoint, *cfg.extra_checkpoints]:
        if not c.is_file():
            raise SystemExit(f"bench/web.py: {c} does not exist; train one with atgs-train and pass its ckpt.pt")
    result = run(cfg)
    for key in ("memory", "bytes"):  # measured by --part memory and --part bytes: kept
        if key in previous:
            result[key] = previous[key]
    publish(result, cfg.out, markdown_table(result), cfg.docs, "web")


if __name__ == "__main__":
    main(tyro.cli(BenchConfig))
