"""Drawing of the bender for ``render_mode="rgb_array"`` and ``"human"`` (matplotlib).

Top: the bent beam from the FE nodal deflections (x in mm, deflection in um: the two axes
have different scales, so a 1 mm stroke on a 40 mm beam is visible), with the clamp.
Bottom: the recent tip-deflection trace and the current reference.
"""

from __future__ import annotations

import numpy as np

from piezo_env.model import PiezoBenderModel

__all__ = ["BenderRenderer"]


class BenderRenderer:
    """Keeps one matplotlib figure and redraws it per frame."""

    def __init__(
        self, model: PiezoBenderModel, *, human: bool = False, size=(6.0, 4.5), dpi=80
    ) -> None:
        import matplotlib

        if not human:
            matplotlib.use("Agg", force=False)
        import matplotlib.pyplot as plt

        self._plt = plt
        self.human = human
        self.model = model
        self.fig, (self.ax_beam, self.ax_trace) = plt.subplots(
            2, 1, figsize=size, dpi=dpi, gridspec_kw={"height_ratios": [3, 2]}
        )
        stroke = model.stroke_um
        x_mm = model.beam.node_positions * 1e3
        self.ax_beam.set_xlim(-0.08 * x_mm[-1], 1.05 * x_mm[-1])
        self.ax_beam.set_ylim(-1.6 * stroke, 1.6 * stroke)
        self.ax_beam.axvspan(-0.08 * x_mm[-1], 0.0, color="0.6")
        self.ax_beam.axhline(0.0, color="0.85", lw=0.8)
        self.ax_beam.set_xlabel("position along the bender (mm)")
        self.ax_beam.set_ylabel("deflection (um)")
        self.ax_beam.set_title(model.name)
        (self.beam_line,) = self.ax_beam.plot(
            x_mm, np.zeros_like(x_mm), "-o", color="tab:orange", lw=3, ms=3
        )
        (self.tip_marker,) = self.ax_beam.plot([x_mm[-1]], [0.0], "s", color="tab:red")
        (self.ref_marker,) = self.ax_beam.plot(
            [x_mm[-1]], [np.nan], "_", color="tab:blue", ms=20, mew=2
        )
        self.time_text = self.ax_beam.text(0.02, 0.92, "", transform=self.ax_beam.transAxes)
        self.ax_trace.set_ylim(-1.6 * stroke, 1.6 * stroke)
        self.ax_trace.set_xlabel("samples ago")
        self.ax_trace.set_ylabel("tip (um)")
        self.ax_trace.axhline(0.0, color="0.85", lw=0.8)
        self._x_mm = x_mm
        self._trace_line = None
        self.fig.tight_layout()
        if human:
            plt.ion()
            plt.show(block=False)

    def draw(
        self,
        nodal_um: np.ndarray,
        tip_um: float,
        trace_um: np.ndarray,
        reference_um: float | None,
        step: int,
    ) -> np.ndarray:
        """Redraw and return the frame as an (H, W, 3) uint8 array."""
        # The nodal shape comes from the modes carried as states; the one-sample residue of the
        # dropped high modes is added in the static uniform-moment shape (x / L)^2.
        shape = np.asarray(nodal_um, dtype=float)
        shape = shape + (tip_um - shape[-1]) * (self._x_mm / self._x_mm[-1]) ** 2
        self.beam_line.set_ydata(shape)
        self.tip_marker.set_ydata([tip_um])
        self.ref_marker.set_ydata([np.nan if reference_um is None else reference_um])
        self.time_text.set_text(f"t = {step * self.model.dt:.3f} s   tip = {tip_um:7.1f} um")
        lags = np.arange(len(trace_um))[::-1]
        if self._trace_line is None:
            (self._trace_line,) = self.ax_trace.plot(lags, trace_um, color="tab:red", lw=1)
            self.ax_trace.set_xlim(lags[0], 0)
        else:
            self._trace_line.set_ydata(trace_um)
        self.fig.canvas.draw()
        frame = np.asarray(self.fig.canvas.buffer_rgba())[..., :3].copy()
        if self.human:
            self._plt.pause(1e-3)
        return frame

    def close(self) -> None:
        """Close the figure."""
        self._plt.close(self.fig)
