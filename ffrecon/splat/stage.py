"""The splat stage: seed, optimise briefly, clean, export, measure.

``run_splat`` writes, under ``out_dir``: ``splat.ply`` (3DGS layout), ``renders/<view>_{truth,seed,splat}.png``
for a few held-out views, ``flythrough.mp4`` and, on request, ``mesh.ply`` + ``mesh.glb``.
Held-out views (every ``holdout_every``-th frame, starting with the first) are never trained on;
PSNR and SSIM are measured on them for the seed, the optimised and the cleaned (exported) splat.
"""

from __future__ import annotations

import enum
import logging
import time
from collections.abc import Sequence
from dataclasses import dataclass, field, replace
from pathlib import Path

import cv2
import kornia
import numpy as np
import torch

from ffrecon.checks import check_shape, require_finite
from ffrecon.errors import InputError
from ffrecon.export.splat_ply import write_splat_ply
from ffrecon.geometry.poses import camera_centers
from ffrecon.splat.clean import CleanOptions, CleanReport, clean_gaussians
from ffrecon.splat.gaussians import Gaussians
from ffrecon.splat.optimize import (
    OptimizeOptions,
    cpu_threads,
    optimize,
    scene_scale,
    torch_threads,
)
from ffrecon.splat.render import RasterOptions, render
from ffrecon.splat.render_gsplat import gsplat_available
from ffrecon.splat.seed import initial_gaussians, reduce_points
from ffrecon.types import PinholeCamera

logger = logging.getLogger("ffrecon.splat")


class SplatDevice(enum.Enum):
    AUTO = "auto"  # CUDA + gsplat when both are available, else the CPU renderer
    CPU = "cpu"
    CUDA = "cuda"


@dataclass(frozen=True, kw_only=True)
class SplatOptions:
    iterations: int = 3000  # upper bound; on a CPU the time budget usually ends the run first
    max_seconds: float = 120.0  # optimisation budget (seed, cleaning and export not included)
    holdout_every: int = 8  # frames 0, k, 2k, ... are held out for evaluation; 0 = none
    sh_degree: int = 3  # SH degree optimised and written to splat.ply
    max_gaussians: int = 100_000  # cap on the count (seed and densification)
    max_seed_points: int = 60_000  # the seed is voxel-downsampled to at most this many points
    refine_poses: bool = False  # jointly refine the training cameras (first one fixed)
    crop_box: tuple[tuple[float, float, float], tuple[float, float, float]] | None = None  # (lo, hi); None = automatic
    mesh: bool = False  # Poisson mesh of the seed cloud: mesh.ply and mesh.glb
    video: bool = True  # flythrough.mp4 along a smooth path through the cameras
    video_frames: int = 90
    report_views: int = 3  # held-out views rendered into renders/ for the report
    background: tuple[float, float, float] = (0.0, 0.0, 0.0)
    seed: int = 0
    device: SplatDevice | str = SplatDevice.AUTO
    threads: int | None = None  # torch CPU threads; None = all available cores but one (see optimize.cpu_threads)
    progress: bool = True
    optimizer: OptimizeOptions = field(default_factory=OptimizeOptions.brief)  # advanced; the fields above override it
    clean: CleanOptions = field(default_factory=CleanOptions)  # crop_box above overrides its crop_box
    raster: RasterOptions = field(default_factory=RasterOptions)


@dataclass(frozen=True)
class ViewMetrics:
    name: str
    psnr_seed: float
    ssim_seed: float
    psnr_optimized: float
    ssim_optimized: float
    psnr_cleaned: float
    ssim_cleaned: float


@dataclass(frozen=True)
class SplatResult:
    out_dir: Path
    ply_path: Path
    renders_dir: Path
    render_paths: tuple[tuple[str, Path, Path, Path], ...]  # (view, truth, seed, splat) PNGs
    video_path: Path | None
    mesh_ply_path: Path | None
    mesh_glb_path: Path | None
    heldout: tuple[ViewMetrics, ...]
    timings: dict[str, float]  # seconds per step
    iterations: int
    iterations_per_second: float
    count_seed: int
    count_optimized: int  # before cleaning
    count_cleaned: int  # written to splat.ply
    clean: CleanReport
    backend: str  # "cpu" (ffrecon's renderer) or "gsplat"
    cam_from_world: np.ndarray = field(repr=False)  # [N, 3, 4] the cameras used (refined when refine_poses)

    def mean(self, key: str) -> float:
        """Mean over held-out views of a :class:`ViewMetrics` field (nan without held-out views)."""
        return float(np.mean([getattr(v, key) for v in self.heldout])) if self.heldout else float("nan")

    def report_images(self) -> list[tuple[str, Path]]:
        """``(caption, PNG path)`` for report.html: per reported held-out view, truth, seed and splat."""
        by_name = {v.name: v for v in self.heldout}
        out = []
        for name, truth, seed, splat in self.render_paths:
            m = by_name[name]
            out += [
                (f"{name}: ground truth", truth),
                (f"{name}: seed, PSNR {m.psnr_seed:.1f} dB", seed),
                (f"{name}: splat, PSNR {m.psnr_cleaned:.1f} dB", splat),
            ]
        return out

    def to_report(self) -> dict:
        """JSON-serialisable section for report.json; paths relative to ``out_dir``."""

        def rel(p: Path | None) -> str | None:
            return None if p is None else str(Path(p).relative_to(self.out_dir))

        keys = ("psnr_seed", "ssim_seed", "psnr_optimized", "ssim_optimized", "psnr_cleaned", "ssim_cleaned")
        return {
            "backend": self.backend,
            "splat_ply": rel(self.ply_path),
            "renders": [
                {"view": v, "truth": rel(t), "seed": rel(s), "splat": rel(o)} for v, t, s, o in self.render_paths
            ],
            "video": rel(self.video_path),
            "mesh": {"ply": rel(self.mesh_ply_path), "glb": rel(self.mesh_glb_path)} if self.mesh_ply_path else None,
            "heldout_views": [v.name for v in self.heldout],
            "heldout_mean": {k: (None if np.isnan(self.mean(k)) else self.mean(k)) for k in keys},
            "heldout_per_view": [{"name": v.name, **{k: getattr(v, k) for k in keys}} for v in self.heldout],
            "iterations": self.iterations,
            "iterations_per_second": self.iterations_per_second,
            "gaussians": {"seed": self.count_seed, "optimized": self.count_optimized, "cleaned": self.count_cleaned},
            "cleaning": self.clean.to_dict(),
            "timings_s": dict(self.timings),
        }


def image_metrics(rendered: torch.Tensor, truth: torch.Tensor) -> tuple[float, float]:
    """PSNR (dB) and SSIM (kornia, 11x11 Gaussian window) of ``[H, W, 3]`` images in [0, 1]."""
    a = rendered.clamp(0, 1).permute(2, 0, 1)[None].float()
    b = truth.permute(2, 0, 1)[None].float()
    mse = float(torch.mean((a - b) ** 2))
    psnr = 10 * np.log10(1.0 / max(mse, 1e-12))
    ssim = float(kornia.metrics.ssim(a, b, 11).mean())
    return float(psnr), ssim


def render_view(g: Gaussians, cam_from_world: np.ndarray, camera: PinholeCamera, options: SplatOptions) -> torch.Tensor:
    """``[H, W, 3]`` render of ``g`` on the CPU (no gradient)."""
    with torch.no_grad():
        out = render(
            g.means,
            g.quats_wxyz,
            g.log_scales,
            g.opacity_logits,
            g.sh,
            torch.tensor(cam_from_world, dtype=torch.float32),
            torch.tensor(camera.K, dtype=torch.float32),
            camera.width,
            camera.height,
            background=torch.tensor(options.background, dtype=torch.float32),
            sh_degree=g.sh_degree,
            with_depth=False,
            options=options.raster,
        )
    return out.rgb.clamp(0, 1)


def _write_png(path: Path, rgb: torch.Tensor | np.ndarray) -> Path:
    arr = rgb if isinstance(rgb, np.ndarray) else (rgb.numpy() * 255 + 0.5).astype(np.uint8)
    cv2.imwrite(str(path), cv2.cvtColor(arr, cv2.COLOR_RGB2BGR))
    return path


def _validate(images, names, cam_from_world, cameras, seed_xyz, seed_rgb) -> None:
    n = len(images)
    if not (len(names) == n == len(cameras) == len(cam_from_world)):
        raise InputError(
            f"run_splat: {n} images, {len(names)} names, {len(cameras)} cameras, {len(cam_from_world)} poses",
            "pass one of each per frame",
        )
    check_shape("cam_from_world", np.asarray(cam_from_world), (n, 3, 4))
    check_shape("seed_xyz", np.asarray(seed_xyz), (None, 3))
    check_shape("seed_rgb", np.asarray(seed_rgb), (len(seed_xyz), 3))
    require_finite(
        "splat",
        cam_from_world=cam_from_world,
        seed_xyz=seed_xyz,
        seed_rgb=seed_rgb,
        intrinsics=np.array([[c.fx, c.fy, c.cx, c.cy] for c in cameras]),
    )
    for name, image, cam in zip(names, images, cameras):
        check_shape(f"image {name}", image, (cam.height, cam.width, 3))


def split_views(num: int, holdout_every: int) -> tuple[list[int], list[int]]:
    """``(train, heldout)`` indices: every ``holdout_every``-th frame from 0 is held out (none if 0 or
    if that would leave no training view).

    >>> split_views(10, 8)
    ([1, 2, 3, 4, 5, 6, 7, 9], [0, 8])
    """
    test = [i for i in range(num) if holdout_every > 0 and i % holdout_every == 0]
    train = [i for i in range(num) if i not in test]
    return (train, test) if train else (list(range(num)), [])


def resolve_device(device: SplatDevice | str) -> str:
    device = SplatDevice(device)
    if device is SplatDevice.CUDA and not gsplat_available():
        raise InputError(
            "device 'cuda' needs CUDA and gsplat", "install ffrecon[gpu] on a CUDA machine, or use device 'auto'"
        )
    return "cuda" if device is SplatDevice.CUDA or (device is SplatDevice.AUTO and gsplat_available()) else "cpu"


def run_splat(
    images: Sequence[np.ndarray],
    names: Sequence[str],
    cam_from_world: np.ndarray,
    cameras: Sequence[PinholeCamera],
    seed_xyz: np.ndarray,
    seed_rgb: np.ndarray,
    options: SplatOptions,
    out_dir: Path,
) -> SplatResult:
    """Seed, optimise, clean and export a Gaussian splat; measure it on held-out views.

    Args:
        images: per frame ``[H, W, 3]`` uint8 RGB.
        names: per frame file names (held-out renders are named after their stem).
        cam_from_world: ``[N, 3, 4]`` OpenCV poses; cameras: per frame pinhole intrinsics.
        seed_xyz: ``[M, 3]`` world points; seed_rgb: ``[M, 3]`` float colours in [0, 1].
    """
    with torch_threads(cpu_threads(options.threads)):
        return _run_splat(images, names, cam_from_world, cameras, seed_xyz, seed_rgb, options, out_dir)


def _run_splat(
    images, names, cam_from_world, cameras, seed_xyz, seed_rgb, options: SplatOptions, out_dir: Path
) -> SplatResult:
    t_start = time.perf_counter()
    _validate(images, names, cam_from_world, cameras, seed_xyz, seed_rgb)
    out_dir = Path(out_dir)
    renders_dir = out_dir / "renders"
    renders_dir.mkdir(parents=True, exist_ok=True)
    timings: dict[str, float] = {}
    device = resolve_device(options.device)
    cam_from_world = np.asarray(cam_from_world, np.float64)
    train, test = split_views(len(images), options.holdout_every)
    logger.info("splat: %d training and %d held-out views, device %s", len(train), len(test), device)

    t = time.perf_counter()
    cap = min(options.max_seed_points, options.max_gaussians)
    xyz, rgb = reduce_points(
        np.asarray(seed_xyz, np.float64),
        np.asarray(seed_rgb, np.float32),
        voxel_size=None,
        max_points=cap,
        seed=options.seed,
    )
    seed = initial_gaussians(xyz, rgb, sh_degree=options.sh_degree)
    scale = scene_scale(cam_from_world[train], xyz)
    timings["seed"] = time.perf_counter() - t

    targets = [torch.from_numpy(np.ascontiguousarray(im)).float() / 255.0 for im in images]
    opt = replace(
        options.optimizer,
        iterations=options.iterations,
        max_seconds=options.max_seconds,
        sh_degree=options.sh_degree,
        max_gaussians=options.max_gaussians,
        refine_poses=options.refine_poses,
        background=options.background,
        raster=options.raster,
        device=device,
        seed=options.seed,
        progress=options.progress,
        threads=options.threads,
    )
    Ks = np.stack([c.K for c in cameras])
    result = optimize(seed, targets, cam_from_world, Ks, train, opt, scale=scale)
    poses = result.cam_from_world
    timings["optimize"] = result.seconds

    t = time.perf_counter()
    clean_opts = replace(options.clean, crop_box=options.crop_box) if options.crop_box is not None else options.clean
    cleaned, clean_report = clean_gaussians(result.gaussians, poses[train], [cameras[i] for i in train], clean_opts)
    timings["clean"] = time.perf_counter() - t

    t = time.perf_counter()
    heldout, render_paths = [], []
    for j, i in enumerate(test):
        views = {
            key: render_view(g, poses[i], cameras[i], options)
            for key, g in (("seed", seed), ("optimized", result.gaussians), ("cleaned", cleaned))
        }
        m = {key: image_metrics(img, targets[i]) for key, img in views.items()}
        heldout.append(ViewMetrics(names[i], *m["seed"], *m["optimized"], *m["cleaned"]))
        if j < options.report_views:
            stem = Path(names[i]).stem
            paths = tuple(
                _write_png(renders_dir / f"{stem}_{kind}.png", img)
                for kind, img in (("truth", images[i]), ("seed", views["seed"]), ("splat", views["cleaned"]))
            )
            render_paths.append((names[i], *paths))
    timings["evaluate"] = time.perf_counter() - t

    t = time.perf_counter()
    ply_path = write_splat_ply(out_dir / "splat.ply", cleaned, sh_degree=options.sh_degree)
    timings["write_ply"] = time.perf_counter() - t

    video_path = None
    if options.video:
        from ffrecon.export.video import write_flythrough

        t = time.perf_counter()
        video_path = write_flythrough(
            out_dir / "flythrough.mp4",
            cleaned,
            poses,
            cameras[0],
            num_frames=options.video_frames,
            background=options.background,
            raster=options.raster,
        )
        timings["video"] = time.perf_counter() - t

    mesh_ply = mesh_glb = None
    if options.mesh:
        from ffrecon.export.mesh import write_mesh

        t = time.perf_counter()
        mesh_ply, mesh_glb = write_mesh(
            out_dir / "mesh.ply",
            out_dir / "mesh.glb",
            np.asarray(seed_xyz, np.float64),
            np.asarray(seed_rgb, np.float32),
            camera_centers(poses),
        )
        timings["mesh"] = time.perf_counter() - t
    timings["total"] = time.perf_counter() - t_start

    res = SplatResult(
        out_dir=out_dir,
        ply_path=ply_path,
        renders_dir=renders_dir,
        render_paths=tuple(render_paths),
        video_path=video_path,
        mesh_ply_path=mesh_ply,
        mesh_glb_path=mesh_glb,
        heldout=tuple(heldout),
        timings=timings,
        iterations=result.iterations,
        iterations_per_second=result.iterations / max(result.seconds, 1e-9),
        count_seed=len(seed),
        count_optimized=len(result.gaussians),
        count_cleaned=len(cleaned),
        clean=clean_report,
        backend="gsplat" if device == "cuda" else "cpu",
        cam_from_world=poses,
    )
    if heldout:
        logger.info(
            "splat: held-out PSNR %.2f -> %.2f dB (cleaned %.2f), SSIM %.3f -> %.3f; %d iterations (%.2f it/s)",
            res.mean("psnr_seed"),
            res.mean("psnr_optimized"),
            res.mean("psnr_cleaned"),
            res.mean("ssim_seed"),
            res.mean("ssim_optimized"),
            res.iterations,
            res.iterations_per_second,
        )
    return res
