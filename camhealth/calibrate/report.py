"""Calibration report: figures (PNG, matplotlib's Agg backend) and a Markdown page.

``DIR/calibration.png`` — four panels: the photon-transfer curve (shot-noise variance vs signal, all gains
at 0 dB scale, with the fitted K0), the dark variance vs exposure per temperature with the Eq. 3.14 law fit,
the dark current vs temperature (per-temperature fits and the law), and the normalised residuals of both
fits. ``DIR/maps.png`` — hot pixels, DSNU and PRNU maps. ``DIR/report.md`` — the metadata with uncertainty
and source, EMVA 1288 figures, every set, the warnings.
"""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np

from camhealth.calibrate.dark_signal import arrhenius_factor
from camhealth.calibrate.result import CalibrationResult
from camhealth.physics.metadata import FULL_FIELDS

__all__ = ["write_report"]


def _figure(result: CalibrationResult, path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    ptc, dark = result.photon_transfer, result.dark
    k0 = ptc.k0
    fig, axes = plt.subplots(2, 2, figsize=(11, 8.5))
    # (a) photon transfer
    ax = axes[0, 0]
    gains = sorted({p.gain_db for p in ptc.used})
    for gdb in gains:
        sel = np.array([p.gain_db == gdb for p in ptc.used])
        g2 = np.array([p.gain_factor for p in ptc.used])[sel]
        # at 0 dB scale (K = g·K0): signal (µ − µ_d)/g = x/g², variance y/g², so that y/g² = K0 · x/g²
        ax.errorbar(ptc.x[sel] / g2**2, ptc.y[sel] / g2**2, yerr=ptc.y_err[sel] / g2**2, fmt="o", ms=4, label=f"flats at {gdb:g} dB")
    xs = np.linspace(0, max(float((ptc.x / np.array([p.gain_factor for p in ptc.used]) ** 2).max()), 1e-9) * 1.05, 50)
    ax.plot(xs, k0 * xs, "k-", lw=1, label=f"K0 = {k0:.4g} ± {ptc.k0_err:.2g} DN/e⁻ (FW {255 / k0:.4g} e⁻)")
    ax.set_xlabel("signal µ − µ_dark, scaled to 0 dB [DN]")
    ax.set_ylabel("σ²_flat − σ²_dark, scaled to 0 dB [DN²]")
    ax.set_title("photon transfer (EMVA 1288)")
    ax.legend(fontsize=8)
    # (b) dark variance vs exposure
    ax = axes[0, 1]
    pts = dark.points
    for j, t in enumerate(dark.temperatures_k):
        sel = [p for p in pts if abs(p.temperature_k - t) < 1e-6]
        ex = np.array([p.exposure_s for p in sel])
        eb = ax.errorbar(ex, [p.y / k0**2 for p in sel], yerr=[p.y_err / k0**2 for p in sel], fmt="o", ms=4, label=f"{t - 273.15:g} °C")
        tt = np.linspace(0, ex.max() * 1.05, 20)
        ax.plot(tt, (dark.intercept_dn2[j] + dark.c_dn2 * float(arrhenius_factor(t)) * tt) / k0**2, "-", lw=1, color=eb[0].get_color())
    ax.set_xlabel("exposure [s]")
    ax.set_ylabel("temporal dark variance [e⁻²]")
    ax.set_title("dark signal: σ_RN² + DC(T)·t (Eq. 3.14 law fit)")
    ax.legend(fontsize=8)
    # (c) dark current vs temperature
    ax = axes[1, 0]
    t = dark.temperatures_k
    dc = dark.free_slope_dn2_per_s / k0**2
    err = dark.free_slope_err / k0**2
    ok = np.isfinite(dc)
    ax.errorbar(t[ok] - 273.15, dc[ok], yerr=err[ok], fmt="o", label="per temperature (free fit)")
    tt = np.linspace(min(t.min(), 273.15), max(t.max(), 273.15 + 80), 60)
    c_e = dark.c_dn2 / k0**2
    if c_e > 0:
        ax.plot(tt - 273.15, c_e * arrhenius_factor(tt), "k-", lw=1, label=f"Eq. 3.14, D_FM = {result.fields['dark_fom_na_per_cm2'].value:.4g} nA/cm²")
    if (dc[ok] > 0).all() and c_e > 0:
        ax.set_yscale("log")
    ax.set_xlabel("sensor temperature [°C]")
    ax.set_ylabel("dark current [e⁻/s]")
    ax.set_title("dark current vs temperature")
    ax.legend(fontsize=8)
    # (d) residuals
    ax = axes[1, 1]
    ax.plot(np.arange(len(ptc.residuals)), ptc.residuals, "o", label=f"photon transfer (χ²/dof {ptc.chi2_dof:.2f})")
    ax.plot(np.arange(len(dark.residuals)) + len(ptc.residuals) + 1, dark.residuals, "s", label=f"dark law (χ²/dof {dark.chi2_dof:.2f})")
    ax.axhline(0, color="k", lw=0.8)
    for v in (-2, 2):
        ax.axhline(v, color="gray", lw=0.6, ls="--")
    ax.set_xlabel("set")
    ax.set_ylabel("residual / σ")
    ax.set_title("fit residuals (normalised)")
    ax.legend(fontsize=8)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


def _maps_figure(result: CalibrationResult, path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    m = result.maps
    fig, axes = plt.subplots(1, 3, figsize=(12, 4))
    dead = m.get("dead_pixels", np.zeros_like(m["hot_pixels"]))
    axes[0].imshow(m["hot_pixels"].astype(np.int8) - dead.astype(np.int8), cmap="coolwarm", vmin=-1, vmax=1, interpolation="nearest")
    axes[0].set_title(f"hot (red) {int(m['hot_pixels'].sum())}, dead (blue) {int(dead.sum())}")
    for ax, key, title in ((axes[1], "dsnu_dn", "DSNU: master bias − mean [DN]"), (axes[2], "prnu", "PRNU: flat / mean − 1")):
        v = m[key]
        lim = float(np.percentile(np.abs(v), 99.5)) or 1e-9
        im = ax.imshow(v, cmap="coolwarm", vmin=-lim, vmax=lim, interpolation="nearest")
        ax.set_title(title)
        fig.colorbar(im, ax=ax, fraction=0.046)
    for ax in axes:
        ax.set_xticks([])
        ax.set_yticks([])
    fig.tight_layout()
    fig.savefig(path, dpi=100)
    plt.close(fig)


def _num(v, spec: str = ".4g") -> str:
    if v is None or (isinstance(v, float) and not math.isfinite(v)):
        return "–"
    return format(v, spec)


def write_report(result: CalibrationResult, directory: str | Path, command: str = "") -> Path:
    """Write ``calibration.png``, ``maps.png`` and ``report.md`` into ``directory``; returns the Markdown path."""
    d = Path(directory)
    d.mkdir(parents=True, exist_ok=True)
    _figure(result, d / "calibration.png")
    _maps_figure(result, d / "maps.png")
    e = result.emva
    lines = ["# Camera calibration", ""]
    if command:
        lines += [f"Command: `{command}`", ""]
    lines += ["## Metadata (camera.yaml)", "", "| field | value | ± 1σ | unit | source | method |", "|---|---:|---:|---|---|---|"]
    for n in FULL_FIELDS:
        fe = result.fields[n]
        unc = _num(fe.uncertainty) + (f" ({100 * fe.relative:.2g} %)" if fe.uncertainty and math.isfinite(fe.relative) else "") if fe.uncertainty else "–"
        lines.append(f"| {n} | {_num(fe.value, '.6g')} | {unc} | {fe.unit} | {fe.source} | {fe.method} |")
    lines += [
        "", "## EMVA 1288 figures", "",
        f"- system gain K at 0 dB: {_num(e['system_gain_k_dn_per_e_at_0db'])} ± {_num(e['system_gain_err'], '.2g')} DN/e⁻ (8-bit DN)",
        f"- saturation capacity (full well at 255 DN, 0 dB): {_num(e['saturation_capacity_e_at_0db'])} e⁻",
        f"- temporal dark noise at {e['temporal_dark_noise_at_c']:g} °C: {_num(e['temporal_dark_noise_e'])} e⁻",
        f"- dynamic range: {_num(e['dynamic_range_db'], '.1f')} dB; SNR max: {_num(e['snr_max_db'], '.1f')} dB",
        f"- dark current at {e['temporal_dark_noise_at_c']:g} °C (Eq. 3.14 law): {_num(e['dark_current_law_e_per_s_at_ref'])} e⁻/s",
        f"- doubling temperature: {_num(e['doubling_temperature_k'], '.3g')} ± {_num(e['doubling_temperature_err'], '.2g')} K measured, "
        f"{_num(e['doubling_temperature_of_eq_3_14_k'], '.3g')} K by Eq. 3.14",
        f"- DSNU: {_num(e['dsnu_e'], '.3g')} e⁻; PRNU: {_num(e['prnu_percent'], '.3g')} %; hot pixels: {e['hot_pixels']}; dead pixels: {e.get('dead_pixels', 0)}",
        "", "| temperature | dark current (free fit) [e⁻/s] | Eq. 3.14 law [e⁻/s] | temporal dark noise [e⁻] |", "|---|---:|---:|---:|",
    ]
    for t, v in e["dark_current"].items():
        dc = "–" if v["dark_current_e_per_s"] is None else f"{v['dark_current_e_per_s']:.4g} ± {_num(v['dark_current_err'], '.2g')}"
        lines.append(f"| {t} | {dc} | {v['law_e_per_s']:.4g} | {v['temporal_dark_noise_e']:.4g} |")
    lines += [
        "", "## Figures", "", "![photon transfer, dark signal, dark current, residuals](calibration.png)", "",
        "![hot pixels, DSNU, PRNU](maps.png)", "", "## Sets", "",
        "| set | kind | exposure [s] | gain [dB] | T [°C] | frames | mean [DN] | σ [DN] | method | clipped low/high [%] | Alg. 1 σ [DN] | used |",
        "|---|---|---:|---:|---:|---:|---:|---:|---|---:|---:|---|",
    ]
    for s in result.sets:
        lines.append(
            f"| {s.name} | {s.kind} | {s.exposure_s:g} | {s.gain_db:g} | {s.temperature_c:g} | {s.n_frames} | {s.mean_dn:.4g} | "
            f"{s.sigma_dn:.4g} ± {_num(s.sigma_err_dn, '.2g')} | {s.method} | {100 * s.clipped_low:.2g}/{100 * s.clipped_high:.2g} | "
            f"{s.mirrored_sigma_dn:.4g} | {'yes' if s.used else 'no: ' + s.note} |"
        )
    if result.warnings:
        lines += ["", "## Warnings", ""] + [f"- {w}" for w in result.warnings]
    path = d / "report.md"
    path.write_text("\n".join(lines) + "\n", encoding="utf-8")
    return path
