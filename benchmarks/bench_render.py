"""Rendering speed: OpenGL (moderngl on EGL, Mesa llvmpipe) against the numpy rasteriser.

Each frame does what the preview does: blend the rig (``Rig.pose``), rotate the head,
compute normals, draw at 512×512 and read the picture back as an RGB array.

    python benchmarks/bench_render.py             # 10k-vertex mesh and the demo-sized face mesh
    python benchmarks/bench_render.py --seconds 5 --repeats 5

Prints a markdown table (best of a few runs: the machines are shared, so the best run is the one
least disturbed). "CPU ms/frame" counts every thread of the process (llvmpipe renders on all
cores). The goal (issue 6) is >= 60 frames/s at 512×512 for a 10k-vertex mesh.
"""

from __future__ import annotations

import argparse
import os
import platform
import time

import numpy as np

from keyshape.containers import Rig
from keyshape.render import frame_points, make_renderer


def grid_rig(side: int, n_targets: int = 8, seed: int = 0) -> Rig:
    """A face-sized curved sheet of ``side²`` vertices with smooth random targets."""
    u, v = np.meshgrid(np.linspace(-1, 1, side), np.linspace(-1.2, 1.2, side))
    x, y = 0.075 * u.ravel(), 0.1 * v.ravel()
    z = 0.06 * np.sqrt(np.clip(1 - u.ravel() ** 2 * 0.8 - (v.ravel() / 1.2) ** 2 * 0.8, 0, 1))
    vertices = np.stack([x, y, z], axis=1)
    i, j = np.meshgrid(np.arange(side - 1), np.arange(side - 1), indexing="ij")
    a = (i * side + j).ravel()
    faces = np.concatenate([np.stack([a, a + 1, a + side], 1), np.stack([a + 1, a + side + 1, a + side], 1)])
    rng = np.random.default_rng(seed)
    centres = rng.uniform(-1, 1, (n_targets, 2))
    bumps = np.exp(-((u.ravel()[None] - centres[:, :1]) ** 2 + (v.ravel()[None] - centres[:, 1:]) ** 2) / 0.1)
    deltas = bumps[:, :, None] * rng.normal(0, 0.01, (n_targets, 1, 3))
    return Rig(vertices, faces, deltas, tuple(f"t{k}" for k in range(n_targets)))


def frames_per_second(rig: Rig, backend: str, *, size: int, seconds: float) -> tuple[float, float, str]:
    """(frames per wall-clock second, CPU milliseconds per frame (all threads), renderer name)."""
    rng = np.random.default_rng(1)
    weights = np.clip(rng.normal(0.3, 0.3, (64, rig.n_targets)), 0, 1)
    angles = np.radians(10) * np.sin(np.linspace(0, 2 * np.pi, 64))
    rotations = np.array([[[np.cos(t), 0, np.sin(t)], [0, 1, 0], [-np.sin(t), 0, np.cos(t)]] for t in angles])
    camera = frame_points(rig.pose(weights) @ rotations.transpose(0, 2, 1), fov_deg=25)
    with make_renderer(rig.faces, size, size, n_vertices=rig.n_vertices, backend=backend) as renderer:
        renderer.render(rig.vertices, camera)  # warm-up (shader compilation)
        count, start, cpu = 0, time.perf_counter(), time.process_time()
        while time.perf_counter() - start < seconds:
            f = count % 64
            image = renderer.render(rig.pose(weights[f:f + 1])[0] @ rotations[f].T, camera)
            count += 1
        elapsed, cpu = time.perf_counter() - start, time.process_time() - cpu
        name = getattr(renderer, "renderer_name", "numpy")
    assert image.shape == (size, size, 3)
    return count / elapsed, 1000 * cpu / count, name


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--seconds", type=float, default=3.0, help="time per measurement (default 3)")
    parser.add_argument("--repeats", type=int, default=3, help="measurements per row; the best is shown")
    parser.add_argument("--size", type=int, default=512)
    args = parser.parse_args()
    meshes = {"10k vertices (100×100 grid)": grid_rig(100), "demo face size (22×22 grid, 484 vertices)": grid_rig(22)}
    rows = []
    for label, rig in meshes.items():
        for backend in ("gl", "numpy"):
            runs = [frames_per_second(rig, backend, size=args.size, seconds=args.seconds) for _ in range(args.repeats)]
            fps, cpu_ms, name = max(runs)
            rows.append((label, rig.n_vertices, len(rig.faces), backend, name, fps, cpu_ms))
    print(f"\nrender benchmark, {args.size}×{args.size}, {platform.machine()}, {os.cpu_count()} CPUs, "
          f"load average {os.getloadavg()[0]:.1f}; best of {args.repeats} × {args.seconds:g} s\n")
    print("| mesh | vertices | triangles | backend | renderer | frames/s | CPU ms/frame |")
    print("|---|---:|---:|---|---|---:|---:|")
    for label, n_vertices, n_faces, backend, name, fps, cpu_ms in rows:
        print(f"| {label} | {n_vertices} | {n_faces} | {backend} | {name} | {fps:.1f} | {cpu_ms:.1f} |")


if __name__ == "__main__":
    main()
