"""The DVS pixel model: events from sampled log radiance, with the sensor's effects.

Each pixel keeps a reference level; when its (optionally low-passed) log radiance has moved
by its contrast threshold from the reference, it fires an event, at the time found by linear
interpolation between samples, and the reference moves by one threshold. Effects, each off
unless the scene lists it (sim/scene.py EFFECTS):

- threshold_spread: per-pixel, per-polarity thresholds drawn once, N(C, sigma), at least 0.01;
- background_activity: the reference leaks down, so that a still pixel fires ON events at
  about rate_hz (per-pixel rates spread by 0.1 decades, random phases), as a DVS pixel does;
- shot_noise: ON and OFF events at random times, rate_hz per pixel, not touching the reference;
- hot_pixels: ``count`` random pixels firing ON events at rate_hz (Poisson);
- refractory: an event within period_us of the pixel's previous one is dropped (the reference
  still moves, as in ESIM);
- bandwidth: the log radiance passes a first-order low-pass with cutoff_hz before comparison;
- footprint: the pixel sees the image through a footprint (its photodiode's area and the lens's
  blur) of sigma_px pixels, not at a point. The samples are a point's; under the image's motion
  a footprint is that point's signal averaged over the time the image takes to cross it, so
  the linear radiance passes first-order low-passes in cascade whose impulse response has the
  footprint's spread in time, sigma_px / (the pixel's image speed, set_image_speed), and the
  events are moved back by the cascade's mean delay. Where the motion is across an edge
  this is the footprint; along an edge, or where a nearer surface slides over a farther one,
  it is an approximation (the speed is the pixel's own surface's);
- timestamp_jitter: Gaussian noise on event times; dropped: each event lost with a probability.
"""

from __future__ import annotations

import numba
import numpy as np

# the footprint's low-passes' longest time constant: a pixel whose image takes longer than
# this to cross its footprint changes too slowly for the footprint to matter
MAX_FOOTPRINT_US = 10_000.0
# low-passes in cascade that spread a point's signal as the footprint would: their impulse
# response (a gamma) nears the footprint's Gaussian as they grow; with 4 an edge's events come
# within half the footprint's spread in time of the Gaussian's, the early ones of a strong
# brightening the latest (the gamma has no early tail; tests/sim/test_pixel_model.py)
FOOTPRINT_STAGES = 4


@numba.njit(cache=True)
def _pixel_events(
    times,
    values,
    offsets,
    pixels,
    ref,
    ref_t,
    last_t,
    filt,
    con,
    coff,
    leak,
    refractory,
    tau,
    max_step,
    fp_tau,
    fp,
    out_t,
    out_px,
    out_p,
):
    """Events of each pixel's samples; state arrays (indexed by pixel) carry over between
    calls. Returns the number of events, or -needed when the output is too small."""
    n_out = 0
    capacity = out_t.shape[0]
    for i in range(pixels.shape[0]):
        p = pixels[i]
        a, b = offsets[i], offsets[i + 1]
        c_on, c_off, drift = con[p], coff[p], leak[p] * con[p] * 1e-6  # drift per us
        ft = fp_tau[p] if fp_tau.shape[0] else 0.0
        for k in range(a, b - 1):
            t0, t1 = times[k], times[k + 1]
            x0, x1 = values[k], values[k + 1]
            if t1 <= t0:
                continue
            # sub-steps: to follow the low-pass filters, and to bound the leak's drift
            steps = 1
            if tau > 0:
                steps = max(steps, int(np.ceil((t1 - t0) / max_step)))
            if ft > 0:
                steps = max(steps, int(np.ceil((t1 - t0) / max(ft / 10, 1.0))))
            slope = (x1 - x0) / (t1 - t0)
            for s in range(steps):
                ta = t0 + (t1 - t0) * s / steps
                tb = t0 + (t1 - t0) * (s + 1) / steps
                h = tb - ta
                xa = x0 + slope * (ta - t0)
                xb = x0 + slope * (tb - t0)
                if ft > 0:  # the footprint: low-passes of the linear radiance in cascade
                    la, lb = np.exp(xa), np.exp(xb)  # each stage's input at ta and tb
                    decay = np.exp(-h / ft)
                    for j in range(fp.shape[0]):
                        u = (lb - la) / h
                        fa = fp[j, p]
                        fb = lb - u * ft + (fa - la + u * ft) * decay
                        fp[j, p] = fb
                        la, lb = fa, fb
                    xa = np.log(max(la, 1e-300))
                    xb = np.log(max(lb, 1e-300))
                ya = filt[p]
                if tau > 0:  # exact first-order response to a linear input
                    u = (xb - xa) / h
                    decay = np.exp(-h / tau)
                    yb = xb - u * tau + (ya - xa + u * tau) * decay
                else:
                    yb = xb
                filt[p] = yb
                # d(t) = y(t) - reference(t), linear on [ta, tb] (the leak lowers the reference)
                while True:
                    da = ya - (ref[p] - drift * (ta - ref_t[p]))
                    db = yb - (ref[p] - drift * (tb - ref_t[p]))
                    if db >= c_on and db > da:
                        level, polarity, step = c_on, 1, c_on
                    elif db <= -c_off and db < da:
                        level, polarity, step = -c_off, 0, -c_off
                    else:
                        break
                    frac = (level - da) / (db - da)
                    frac = min(max(frac, 0.0), 1.0)
                    tc = ta + frac * (tb - ta)
                    # the reference at the crossing, moved by one threshold
                    ref[p] = ref[p] - drift * (tc - ref_t[p]) + step
                    ref_t[p] = tc
                    ya = ya + frac * (yb - ya)
                    ta = tc
                    if refractory > 0 and tc - last_t[p] < refractory:
                        continue  # dropped; the reference has moved all the same
                    last_t[p] = tc
                    if n_out < capacity:
                        out_t[n_out] = tc - fp.shape[0] * ft  # the cascade's mean delay
                        out_px[n_out] = p
                        out_p[n_out] = polarity
                    n_out += 1
    if n_out > capacity:
        return -n_out
    return n_out


class PixelArray:
    """The state of every pixel of the sensor, and its (seeded) imperfections."""

    def __init__(
        self,
        n_pixels: int,
        threshold_on: float | np.ndarray,
        threshold_off: float | np.ndarray,
        effects: dict,
        rng: np.random.Generator,
        hot_pixels: np.ndarray | None = None,
    ) -> None:
        """Thresholds: one for all pixels or one per pixel (a measured calibration's maps);
        ``hot_pixels``: which pixels are hot (flat indices; None: drawn at random)."""
        self.n = n_pixels
        self.effects = effects
        self.rng = rng
        on = np.broadcast_to(np.asarray(threshold_on, np.float64), (n_pixels,))
        off = np.broadcast_to(np.asarray(threshold_off, np.float64), (n_pixels,))
        spread = effects.get("threshold_spread")
        if spread:
            sigma = spread["sigma"]
            self.con = np.maximum(rng.normal(on, sigma, n_pixels), 0.01)
            self.coff = np.maximum(rng.normal(off, sigma, n_pixels), 0.01)
        else:
            self.con = on.copy()
            self.coff = off.copy()
        ba = effects.get("background_activity")
        if ba:
            self.leak = ba["rate_hz"] * 10 ** rng.normal(0, 0.1, n_pixels)
        else:
            self.leak = np.zeros(n_pixels)
        hot = effects.get("hot_pixels")
        if hot_pixels is not None:
            self.hot = np.asarray(hot_pixels, np.int64)
        elif hot:
            self.hot = rng.choice(n_pixels, size=min(hot["count"], n_pixels), replace=False)
        else:
            self.hot = np.zeros(0, np.int64)
        self.refractory_us = float(effects.get("refractory", {}).get("period_us", 0))
        cutoff = effects.get("bandwidth", {}).get("cutoff_hz", 0.0)
        self.tau_us = 1e6 / (2 * np.pi * cutoff) if cutoff > 0 else 0.0
        self.footprint_px = float(effects.get("footprint", {}).get("sigma_px", 0.0))
        self.fp_tau = np.zeros(n_pixels if self.footprint_px > 0 else 0)
        # the footprint's low-passes' states (linear radiance)
        self.fp = np.zeros((FOOTPRINT_STAGES, len(self.fp_tau)))
        self.ref = np.zeros(n_pixels)
        self.ref_t = np.zeros(n_pixels)
        self.last_t = np.full(n_pixels, -np.inf)
        self.filt = np.zeros(n_pixels)
        self.started = False

    def start(self, log_values: np.ndarray, t_us: float) -> None:
        """Set every pixel's reference (and filter) to its value at time ``t_us``."""
        self.ref[:] = log_values
        self.filt[:] = log_values
        if self.footprint_px > 0:
            self.fp[:] = np.exp(log_values)
        self.ref_t[:] = t_us
        if self.leak.any():  # random leak phases, so that still pixels do not fire together
            self.ref -= self.rng.random(self.n) * self.con
        self.started = True

    def set_image_speed(self, px_per_us: np.ndarray) -> None:
        """Each pixel's image speed until the next call (pixels a microsecond): the footprint's
        spread in time is sigma_px / speed, each low-pass's time constant that over
        sqrt(FOOTPRINT_STAGES) (each adds its share of the variance), at most
        MAX_FOOTPRINT_US."""
        spread = self.footprint_px / np.maximum(px_per_us, 1e-12)
        self.fp_tau[:] = np.minimum(spread / np.sqrt(FOOTPRINT_STAGES), MAX_FOOTPRINT_US)

    @property
    def max_delay_us(self) -> float:
        """The most an event's time is moved back (the footprint's delay)."""
        return FOOTPRINT_STAGES * MAX_FOOTPRINT_US if self.footprint_px > 0 else 0.0

    def events(
        self, times: np.ndarray, values: np.ndarray, offsets: np.ndarray, pixels: np.ndarray
    ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """(t us float, pixel, polarity) of the events of these pixels' samples (times in us;
        ``offsets`` delimit each pixel's samples)."""
        capacity = max(1024, len(times))
        state = (self.ref, self.ref_t, self.last_t, self.filt, self.fp)
        saved = [s.copy() for s in state]
        while True:
            out_t = np.empty(capacity)
            out_px = np.empty(capacity, np.int64)
            out_p = np.empty(capacity, np.uint8)
            n = _pixel_events(
                times,
                values,
                offsets,
                pixels,
                self.ref,
                self.ref_t,
                self.last_t,
                self.filt,
                self.con,
                self.coff,
                self.leak,
                self.refractory_us,
                self.tau_us,
                max(self.tau_us / 10, 1.0),
                self.fp_tau,
                self.fp,
                out_t,
                out_px,
                out_p,
            )
            if n >= 0:
                return out_t[:n], out_px[:n], out_p[:n]
            capacity = -n
            for s, copy in zip(state, saved, strict=True):
                s[:] = copy

    def noise(self, t0_us: float, t1_us: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Shot noise and hot-pixel events in [t0, t1) (independent of the signal)."""
        ts, pxs, ps = [], [], []
        span = (t1_us - t0_us) * 1e-6
        shot = self.effects.get("shot_noise")
        if shot:
            n = self.rng.poisson(shot["rate_hz"] * self.n * span)
            ts.append(self.rng.uniform(t0_us, t1_us, n))
            pxs.append(self.rng.integers(0, self.n, n))
            ps.append(self.rng.integers(0, 2, n).astype(np.uint8))
        if len(self.hot):
            rate = self.effects["hot_pixels"]["rate_hz"]
            counts = self.rng.poisson(rate * span, len(self.hot))
            ts.append(self.rng.uniform(t0_us, t1_us, counts.sum()))
            pxs.append(np.repeat(self.hot, counts))
            ps.append(np.ones(counts.sum(), np.uint8))
        if not ts:
            return np.zeros(0), np.zeros(0, np.int64), np.zeros(0, np.uint8)
        return np.concatenate(ts), np.concatenate(pxs), np.concatenate(ps)

    def degrade(self, t: np.ndarray, px: np.ndarray, p: np.ndarray):
        """Timestamp jitter and dropped events, on events about to be output."""
        jitter = self.effects.get("timestamp_jitter")
        if jitter:
            t = t + self.rng.normal(0, jitter["sigma_us"], len(t))
        dropped = self.effects.get("dropped")
        if dropped:
            keep = self.rng.random(len(t)) >= dropped["probability"]
            t, px, p = t[keep], px[keep], p[keep]
        return t, px, p
