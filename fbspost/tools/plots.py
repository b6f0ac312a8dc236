"""Plots of a ``simulate.Simulation`` (matplotlib's object API on the Agg canvas: no display).

Takes a Simulation and a file name; writes, atomically, one PNG with every panel or a multi-page
PDF with one panel per page: the path with the contour error magnified (the layer of the
original's worst error), the methods' costs (contour error, the command's departure from the
path, the end delay), the tracking error against time and its spectrum per axis, and each
axis' frequency response with its modes and the shaper frequency. Lines show the original, FBS
and the shaper with the lowest contour error; the cost panel shows every method.
"""
from __future__ import annotations

from pathlib import Path

import numpy as np

from ..firmware.shapers import SHAPERS
from ..read.blocks import AXES
from ..write.atomicfile import atomic_write
from .simulate import Method, Simulation, dominant_mode

FORMATS = (".png", ".pdf")
_COLORS = {"original": "0.45", "fbs": "tab:blue", "shaper": "tab:orange"}


def write_plot(sim: Simulation, path: str | Path) -> None:
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.backends.backend_pdf import PdfPages
    from matplotlib.figure import Figure

    path = Path(path)
    if path.suffix.lower() not in FORMATS:
        raise ValueError(f"{path}: the plot is written as .png or .pdf")
    shown = _shown(sim)
    panels = [lambda ax: _path(ax, sim, shown), lambda ax: _costs(ax, sim)]
    panels += [lambda ax, a=a: _tracking(ax, sim, shown, a) for a in sim.modelled]
    panels += [lambda ax: _spectrum(ax, sim, shown), lambda ax: _response(ax, sim)]
    title = f"{Path(sim.program).name} on {sim.profile.name}: original, FBS and input shapers (model)"
    if path.suffix.lower() == ".png":
        rows = (len(panels) + 1) // 2
        fig = Figure(figsize=(15, 5.2 * rows), layout="constrained")
        FigureCanvasAgg(fig)
        for i, draw in enumerate(panels):
            draw(fig.add_subplot(rows, 2, i + 1))
        fig.suptitle(title, fontsize=14)
        atomic_write(path, lambda f: _save_png(fig, f))
        return

    def pages(f):
        with PdfPages(f) as pdf:
            for draw in panels:
                fig = Figure(figsize=(11, 7.5), layout="constrained")
                FigureCanvasAgg(fig)
                draw(fig.add_subplot())
                fig.suptitle(title)
                pdf.savefig(fig)

    atomic_write(path, pages)


def _save_png(fig, f) -> None:
    """At 72 dpi in 256 colours: the same picture in a third of the bytes."""
    from PIL import Image  # matplotlib's own dependency

    fig.set_dpi(72)
    fig.canvas.draw()
    image = Image.fromarray(np.asarray(fig.canvas.buffer_rgba())).convert("RGB")
    image.quantize(256).save(f, format="png", optimize=True)


def _shown(sim: Simulation) -> list[tuple[Method, str]]:
    """The original, the best shaper and FBS, with their colours."""
    by_name = {m.name: m for m in sim.methods}
    shapers = [m for m in sim.methods if m.name in SHAPERS]
    shown = [(by_name["original"], _COLORS["original"])]
    if shapers:
        shown.append((min(shapers, key=lambda m: m.path.rms_contour_error_um), _COLORS["shaper"]))
    return shown + [(by_name["fbs"], _COLORS["fbs"])]


def _path(ax, sim: Simulation, shown) -> None:
    index = np.flatnonzero(sim.contour_mask)
    original = shown[0][0]
    worst = index[np.argmax(original.contour_error_mm)] if index.size else 0
    layer = np.isclose(sim.desired_mm[index, 2], sim.desired_mm[worst, 2], atol=1e-6)
    if original.contour_error_mm.size and original.contour_error_mm.max() > 0:
        extent = np.ptp(sim.desired_mm[index[layer], :2], axis=0).max()
        gain = _round_125(0.04 * extent / original.contour_error_mm[layer].max())
    else:
        gain = 1.0
    # Pieces of the path on this layer, as one line broken between them.
    on_layer = np.isclose(sim.path_start_mm[:, 2], sim.desired_mm[worst, 2], atol=1e-6)
    segments = np.stack([sim.path_start_mm[on_layer, :2], sim.path_end_mm[on_layer, :2],
                         np.full((on_layer.sum(), 2), np.nan)], axis=1).reshape(-1, 2)
    ax.plot(segments[:, 0], segments[:, 1], color="black", lw=0.8, label="programmed path")
    gaps = np.flatnonzero(np.diff(index[layer]) > 1) + 1
    for method, color in shown:
        near = method.nearest_mm[layer, :2]
        shown_xy = near + gain * (method.actual_mm[index[layer], :2] - near)
        shown_xy = np.insert(shown_xy, gaps, np.nan, axis=0)
        ax.plot(shown_xy[:, 0], shown_xy[:, 1], color=color, lw=1.0,
                label=f"{method.name}: contour RMS {method.path.rms_contour_error_um:.3g} um")
    where = f", layer Z {sim.desired_mm[worst, 2]:g} mm" if sim.printer else ""
    ax.set_title(f"Modelled path, contour error magnified x{gain:g}{where}")
    ax.set_xlabel("X (mm)")
    ax.set_ylabel("Y (mm)")
    ax.set_aspect("equal", adjustable="datalim")
    ax.legend(loc="best", fontsize=8)


def _costs(ax, sim: Simulation) -> None:
    names = [m.name for m in sim.methods]
    x = np.arange(len(names))
    contour = [m.path.rms_contour_error_um for m in sim.methods]
    command = [m.path.rms_command_contour_error_um for m in sim.methods]
    residual = [m.path.residual_vibration_um for m in sim.methods]
    positive = [v for v in contour + command + residual if v > 1e-6]  # below: rounding, nothing
    bottom = min(positive, default=1.0) / 3  # log scale: a zero shows as no bar
    for offset, values, label, color in ((-0.27, contour, "contour error RMS (actual)", "tab:red"),
                                         (0.0, command, "command off path RMS (shaper smoothing)", "tab:purple"),
                                         (0.27, residual, "residual vibration max", "tab:green")):
        ax.bar(x + offset, np.maximum(values, bottom), width=0.27, label=label, color=color)
    ax.set_ylim(bottom, max(positive, default=1.0) * 100)  # room for the legend
    ax.set_yscale("log")
    ax.set_xticks(x, [f"{m.name}\n+{m.path.end_delay_s * 1e3:.1f} ms" for m in sim.methods])
    ax.set_ylabel("um (log)")
    ax.set_title("Cost of each method (below each: how much later the motion ends)")
    ax.legend(loc="upper center", fontsize=8, ncol=3)
    ax.grid(axis="y", which="major", alpha=0.3)


def _tracking(ax, sim: Simulation, shown, axis: str) -> None:
    column = AXES.index(axis)
    for method, color in shown:
        error_um = (sim.desired_mm[:, column] - method.actual_mm[:, column]) * 1e3
        ax.plot(*_envelope(sim.time_s, error_um), color=color, lw=0.6,
                label=f"{method.name}: RMS {method.axes[axis].rms_tracking_error_um:.3g} um")
    ax.set_title(f"Tracking error of axis {axis} (planned - modelled actual)")
    ax.set_xlabel("time (s)")
    ax.set_ylabel(f"{axis} error (um)")
    ax.legend(loc="upper right", fontsize=8)
    ax.grid(alpha=0.3)


def _spectrum(ax, sim: Simulation, shown) -> None:
    period_s = 1.0 / sim.profile.sample_rate_hz
    top_hz = 3 * max(m.frequency_hz for a in sim.modelled for m in sim.profile.axes[a].modes)
    styles = ["-", "--", ":"]  # (for up to three modelled axes)
    for method, color in shown:
        for axis, style in zip(sim.modelled, styles, strict=False):
            error_um = (sim.desired_mm[:, AXES.index(axis)] - method.actual_mm[:, AXES.index(axis)]) * 1e3
            amplitude = 2 * np.abs(np.fft.rfft(error_um)) / len(error_um)  # of a sine at that frequency
            frequency = np.fft.rfftfreq(len(error_um), period_s)
            keep = (frequency > 0) & (frequency <= top_hz)
            ax.plot(*_envelope(frequency[keep], np.maximum(amplitude[keep], 1e-6)), color=color, ls=style, lw=0.8,
                    label=f"{method.name} {axis}")
    ax.set_yscale("log")
    ax.set_title("Spectrum of the tracking error")
    ax.set_xlabel("frequency (Hz)")
    ax.set_ylabel("amplitude (um)")
    ax.legend(loc="upper right", fontsize=8, ncol=len(shown))
    ax.grid(alpha=0.3)


def _response(ax, sim: Simulation) -> None:
    from ..fbs.dynamics import AxisDynamics

    top_hz = 3 * max(m.frequency_hz for a in sim.modelled for m in sim.profile.axes[a].modes)
    frequency = np.linspace(0.1, top_hz, 3000)
    shaped = next((m for m in sim.methods if m.shapers), None)
    for axis in sim.modelled:
        modes = sim.profile.axes[axis].modes
        gain = np.abs(AxisDynamics(modes, 1.0 / sim.profile.sample_rate_hz).frequency_response(frequency))
        line, = ax.plot(frequency, gain, lw=1.2, label=f"{axis}: |G(j 2 pi f)|")
        for j, mode in enumerate(modes):
            ax.axvline(mode.frequency_hz, color=line.get_color(), ls=":", lw=0.8,
                       label=f"{axis} modes: " + ", ".join(f"{m.frequency_hz:g} Hz (z {m.damping:g})" for m in modes)
                       if j == 0 else None)
        if shaped:
            ax.axvline(shaped.shapers[axis].frequency_hz, color=line.get_color(), ls="--", lw=1.0,
                       label=f"{axis}: shaper frequency {shaped.shapers[axis].frequency_hz:g} Hz"
                             + (" (dominant mode)" if shaped.shapers[axis].frequency_hz
                                == dominant_mode(sim.profile.axes[axis]).frequency_hz else ""))
    ax.set_yscale("log")
    low, high = ax.get_ylim()
    ax.set_ylim(low / 100, high)  # room for the legend
    ax.set_xlabel("frequency (Hz)")
    ax.set_title("Frequency response of each axis (commanded to actual), modes dotted")
    ax.set_ylabel("gain (actual / commanded)")
    ax.legend(loc="lower left", fontsize=8)
    ax.grid(alpha=0.3)


def _envelope(x: np.ndarray, y: np.ndarray, bins: int = 2000) -> tuple[np.ndarray, np.ndarray]:
    """Long lines as the minimum and maximum of each of ``bins`` stretches: the same picture, a
    small file."""
    if len(x) <= 2 * bins:
        return x, y
    edges = np.linspace(0, len(x), bins + 1).astype(int)
    low, high = np.minimum.reduceat(y, edges[:-1]), np.maximum.reduceat(y, edges[:-1])
    middle = x[(edges[:-1] + edges[1:]) // 2]
    return np.repeat(middle, 2), np.column_stack([low, high]).ravel()


def _round_125(value: float) -> float:
    """The largest of 1, 2, 5 times a power of ten not above ``value`` (at least 1)."""
    if value <= 1:
        return 1.0
    power = 10 ** np.floor(np.log10(value))
    return float(max(m * power for m in (1, 2, 5) if m * power <= value))
