"""report.html from report.json's data: the splat's held-out quality over time."""

from ffrecon.report import html as report_html

CURVE = [
    {"iteration": 0, "seconds": 0.0, "psnr": 14.5, "ssim": 0.40},
    {"iteration": 20, "seconds": 4.1, "psnr": 19.0, "ssim": 0.62},
    {"iteration": 40, "seconds": 8.3, "psnr": 21.2, "ssim": 0.71},
]


def _splat_section(curve: list[dict]) -> dict:
    mean = {f"{k}_{s}": 20.0 for k in ("psnr", "ssim") for s in ("seed", "optimized", "cleaned")}
    return {
        "heldout_mean": mean,
        "gaussians": {"seed": 100, "optimized": 120, "cleaned": 110},
        "iterations": 40,
        "iterations_per_second": 4.8,
        "heldout_per_view": [],
        "renders": [],
        "heldout_curve": curve,
    }


def test_the_heldout_curve_is_drawn_whenever_the_splat_recorded_one(tmp_path):
    rows, body = report_html._splat({"splat": _splat_section(CURVE)}, tmp_path)
    assert "Held-out quality over optimisation time" in body and body.count("data:image/png;base64,") == 1
    assert rows[0]["measure"] == "held-out PSNR (dB)"
    _, without = report_html._splat({"splat": _splat_section([])}, tmp_path)
    assert "Held-out quality" not in without and "data:image/png" not in without
