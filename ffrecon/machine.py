"""What this machine has free now (shared by the stages that size their work to it)."""

from __future__ import annotations

import os
import subprocess
from pathlib import Path


def _proc_bytes(path: str, field: str) -> int | None:
    """A ``<field>: <n> kB`` line of a Linux /proc file, in bytes; None where it cannot be read."""
    try:
        for line in Path(path).read_text().splitlines():
            if line.startswith(f"{field}:"):
                return int(line.split()[1]) * 1024
    except OSError:
        pass
    return None


def available_memory_bytes() -> int:
    """Memory available to a new allocation now (Linux ``MemAvailable``; else total physical memory)."""
    available = _proc_bytes("/proc/meminfo", "MemAvailable")
    return available if available is not None else os.sysconf("SC_PAGE_SIZE") * os.sysconf("SC_PHYS_PAGES")


def cuda_free_memory_bytes() -> int | None:
    """Free memory on the first CUDA device now, or None when there is none to ask.

    Through torch when its build has CUDA (gsplat's machines), else ``nvidia-smi`` (present wherever
    NVIDIA's driver is, e.g. onnxruntime-gpu beside a CPU build of torch).
    """
    try:
        import torch

        if torch.cuda.is_available():
            return int(torch.cuda.mem_get_info()[0])
    except Exception:  # a broken CUDA install must not stop the run: the caller falls back to host memory
        pass
    try:
        out = subprocess.run(
            ["nvidia-smi", "--query-gpu=memory.free", "--format=csv,noheader,nounits", "--id=0"],
            capture_output=True,
            text=True,
            timeout=10,
            check=True,
        ).stdout
        return int(float(out.split()[0]) * 2**20)
    except (OSError, ValueError, IndexError, subprocess.SubprocessError):
        return None


def reset_peak_rss() -> bool:
    """Reset this process's resident-memory high-water mark (Linux: ``5`` into ``/proc/self/clear_refs``), so
    that :func:`peak_rss_bytes` reads the peak from now on; False where the kernel does not allow it (the
    mark then keeps the whole process's peak)."""
    try:
        Path("/proc/self/clear_refs").write_text("5")
        return True
    except OSError:
        return False


def peak_rss_bytes() -> int | None:
    """This process's resident-memory high-water mark (``VmHWM``; since :func:`reset_peak_rss`), or None."""
    peak = _proc_bytes("/proc/self/status", "VmHWM")
    if peak is not None:
        return peak
    try:
        import resource

        return int(resource.getrusage(resource.RUSAGE_SELF).ru_maxrss) * 1024  # kB on Linux
    except (ImportError, OSError):
        return None
