//! Motion planning: trapezoidal velocity profiles and their compression into
//! step-generator segments.
//!
//! A [`Profile`] gives the exact (real-valued) time of every step of a move.
//! The [`SegmentPlanner`] turns those times into [`Segment`]s of
//! `(interval, count, add)`: over each segment the step times follow a
//! quadratic in the step index, which is fitted through the exact times at the
//! segment's middle and end. The segment length is chosen from an error bound
//! (the third derivative of time over distance, `3a²/v⁵`, bounds the
//! interpolation error) so that every step lands within `ERROR_BUDGET` ticks
//! of its exact time before rounding, and so within one tick after the
//! generator rounds it. Segments never straddle a phase boundary (where the
//! bound does not hold): the step that crosses one gets a segment of its own.
//!
//! All of this runs in thread mode, one segment at a time, so the work per call
//! is bounded; the interrupt never sees floating point.

use libm::{floor, round, sqrt};

use crate::step::{FRAC_BITS, Segment};

/// Largest deviation, in ticks, of a planned (fixed-point) step time from its
/// exact time; the generator's rounding adds at most half a tick more.
pub const ERROR_BUDGET: f64 = 0.3;
/// Longest accelerating segment (bounds the fixed-point rounding of `add`).
const MAX_RAMP_SEGMENT: u32 = 2048;
/// Longest constant-speed segment (bounds the fixed-point rounding of `interval`).
const MAX_CRUISE_SEGMENT: u32 = 1 << 20;
/// max |x (x − m/2)(x − m)| / m³ on [0, m], divided by 3!.
const INTERP_FACTOR: f64 = 0.048_112_522_432_468_82 / 6.0;

const FIXED_ONE: f64 = (1u64 << FRAC_BITS) as f64;

/// A velocity profile over `steps` steps: accelerate from `v0` at `accel` to
/// `v_peak`, cruise, decelerate at `decel` to rest. Speeds in steps/s,
/// accelerations in steps/s², times in seconds from the profile's origin.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Profile {
    steps: u32,
    v0: f64,
    v_peak: f64,
    accel: f64,
    decel: f64,
    /// Distance at the end of the acceleration phase.
    s_acc: f64,
    /// Distance at the start of the deceleration phase.
    s_dec: f64,
    t_acc: f64,
    t_total: f64,
}

/// Phase of a profile.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Phase {
    /// Speeding up.
    Accelerate,
    /// Constant speed.
    Cruise,
    /// Slowing down.
    Decelerate,
}

impl Profile {
    /// A move of `steps` steps from rest to rest (or from `v0`), limited by
    /// `v_max` and `a_max`. A short move becomes a triangle.
    pub fn trapezoid(steps: u32, v0: f64, v_max: f64, a_max: f64) -> Profile {
        Self::with_rates(steps, v0, v_max, a_max, a_max)
    }

    /// A controlled stop from speed `v0`: decelerate at no more than `decel`
    /// over a whole number of steps.
    pub fn stop(v0: f64, decel: f64) -> Profile {
        let steps = libm::ceil(v0 * v0 / (2.0 * decel)).max(0.0) as u32;
        if steps == 0 {
            return Self::with_rates(0, 0.0, 1.0, decel, decel);
        }
        // Exactly `steps` steps to rest: a slightly gentler deceleration.
        let d = v0 * v0 / (2.0 * steps as f64);
        Profile {
            steps,
            v0,
            v_peak: v0,
            accel: d,
            decel: d,
            s_acc: 0.0,
            s_dec: 0.0,
            t_acc: 0.0,
            t_total: v0 / d,
        }
    }

    fn with_rates(steps: u32, v0: f64, v_max: f64, accel: f64, decel: f64) -> Profile {
        let n = steps as f64;
        let v0 = v0.min(v_max).max(0.0);
        let mut v_peak = v_max;
        let mut s_acc = (v_peak * v_peak - v0 * v0) / (2.0 * accel);
        let mut s_dec_len = v_peak * v_peak / (2.0 * decel);
        if s_acc + s_dec_len > n {
            // Triangle: the peak where the two ramps meet.
            v_peak = sqrt((2.0 * n + v0 * v0 / accel) / (1.0 / accel + 1.0 / decel)).max(v0);
            s_acc = ((v_peak * v_peak - v0 * v0) / (2.0 * accel)).max(0.0);
            s_dec_len = n - s_acc;
        }
        let s_dec = n - s_dec_len;
        let t_acc = (v_peak - v0) / accel;
        let t_cruise = if v_peak > 0.0 { (s_dec - s_acc) / v_peak } else { 0.0 };
        let t_total = t_acc + t_cruise + sqrt(2.0 * s_dec_len / decel);
        Profile { steps, v0, v_peak, accel, decel, s_acc, s_dec, t_acc, t_total }
    }

    /// Steps in the move.
    pub fn steps(&self) -> u32 {
        self.steps
    }
    /// Peak speed, steps/s.
    pub fn v_peak(&self) -> f64 {
        self.v_peak
    }
    /// Acceleration used, steps/s².
    pub fn accel(&self) -> f64 {
        self.accel
    }
    /// Deceleration used, steps/s².
    pub fn decel(&self) -> f64 {
        self.decel
    }
    /// Duration, s.
    pub fn duration(&self) -> f64 {
        self.t_total
    }

    /// Phase at distance `s` (the right-hand one at a boundary).
    pub fn phase(&self, s: f64) -> Phase {
        if s < self.s_acc {
            Phase::Accelerate
        } else if s < self.s_dec {
            Phase::Cruise
        } else {
            Phase::Decelerate
        }
    }

    /// Exact time at which the profile has covered `s` steps, s.
    pub fn time_at(&self, s: f64) -> f64 {
        let s = s.clamp(0.0, self.steps as f64);
        if s <= self.s_acc {
            // (√(v0² + 2as) − v0)/a, written without cancellation.
            2.0 * s / (sqrt(self.v0 * self.v0 + 2.0 * self.accel * s) + self.v0)
        } else if s <= self.s_dec {
            self.t_acc + (s - self.s_acc) / self.v_peak
        } else {
            self.t_total - sqrt(2.0 * (self.steps as f64 - s) / self.decel)
        }
    }

    /// Speed at distance `s`, steps/s.
    pub fn velocity_at(&self, s: f64) -> f64 {
        let s = s.clamp(0.0, self.steps as f64);
        if s <= self.s_acc {
            sqrt(self.v0 * self.v0 + 2.0 * self.accel * s)
        } else if s <= self.s_dec {
            self.v_peak
        } else {
            sqrt(2.0 * self.decel * (self.steps as f64 - s))
        }
    }

    /// Bound on |d³t/ds³| (s/step³) over [lo, hi] within one ramp phase.
    fn third_derivative_bound(&self, phase: Phase, lo: f64, hi: f64) -> f64 {
        let (rate, v) = match phase {
            Phase::Cruise => return 0.0,
            Phase::Accelerate => (self.accel, self.velocity_at(lo)),
            Phase::Decelerate => (self.decel, self.velocity_at(hi)),
        };
        if v <= 0.0 {
            return f64::INFINITY;
        }
        let v2 = v * v;
        3.0 * rate * rate / (v2 * v2 * v)
    }
}

/// Turns a [`Profile`] into step-generator segments, one per call.
#[derive(Debug, Clone)]
pub struct SegmentPlanner {
    profile: Profile,
    ticks_per_second: f64,
    planned: u32,
    /// Fixed-point time of the last planned step since the origin.
    elapsed: i128,
}

impl SegmentPlanner {
    /// Plan `profile` on a timer of `tick_hz`.
    pub fn new(profile: Profile, tick_hz: u32) -> Self {
        SegmentPlanner { profile, ticks_per_second: tick_hz as f64, planned: 0, elapsed: 0 }
    }

    /// The profile.
    pub fn profile(&self) -> &Profile {
        &self.profile
    }

    /// Steps planned so far.
    pub fn planned(&self) -> u32 {
        self.planned
    }

    /// Whether every step has been planned.
    pub fn is_done(&self) -> bool {
        self.planned >= self.profile.steps
    }

    /// Exact time of step `k`, ticks since the origin.
    pub fn exact_ticks(&self, k: u32) -> f64 {
        self.profile.time_at(k as f64) * self.ticks_per_second
    }

    /// The next segment, or `None` when the move is fully planned.
    pub fn next_segment(&mut self) -> Option<Segment> {
        let n = self.profile.steps;
        if self.planned >= n {
            return None;
        }
        let k0 = self.planned;
        let x0 = self.elapsed as f64 / FIXED_ONE;
        let segment = self.fit(k0, x0, n).unwrap_or_else(|| self.single(k0, x0));
        self.elapsed += segment.duration();
        self.planned += segment.count;
        Some(segment)
    }

    /// The step `k0 + 1` on its own, exact but for fixed-point rounding.
    fn single(&self, k0: u32, x0: f64) -> Segment {
        let interval = (self.exact_ticks(k0 + 1) - x0).max(1.0);
        Segment { count: 1, interval: round(interval * FIXED_ONE) as u64, add: 0 }
    }

    /// A multi-step segment starting after step `k0`, if one fits the budget.
    fn fit(&self, k0: u32, x0: f64, n: u32) -> Option<Segment> {
        let p = &self.profile;
        let (lo, hi) = (k0 as f64, (k0 + 1) as f64);
        let phase = p.phase(lo);
        if p.phase(hi - 1e-9) != phase || (hi > p.s_acc && lo < p.s_acc) {
            return None; // the first interval straddles a phase boundary
        }
        // Last step index lying wholly inside this phase.
        let last = match phase {
            Phase::Accelerate => floor(p.s_acc) as u32,
            Phase::Cruise => floor(p.s_dec) as u32,
            Phase::Decelerate => n,
        }
        .min(n);
        let max_m = last.checked_sub(k0)?;
        if phase == Phase::Cruise {
            let m = max_m.min(MAX_CRUISE_SEGMENT);
            if m < 2 {
                return None;
            }
            let interval = (self.exact_ticks(k0 + m) - x0) / m as f64;
            return Some(Segment {
                count: m,
                interval: round(interval * FIXED_ONE) as u64,
                add: 0,
            });
        }

        // The error bound grows with m: binary-search the longest admissible m.
        let err = |m: u32| {
            let j = p.third_derivative_bound(phase, lo, (k0 + m) as f64) * self.ticks_per_second;
            let mf = m as f64;
            INTERP_FACTOR * j * mf * mf * mf + (mf + mf * mf / 2.0) / (2.0 * FIXED_ONE)
        };
        let (mut good, mut bad) = (2u32, max_m.min(MAX_RAMP_SEGMENT) + 1);
        if err(3) > ERROR_BUDGET || bad <= 3 {
            return None;
        }
        while bad - good > 1 {
            let mid = good + (bad - good) / 2;
            if err(mid) <= ERROR_BUDGET { good = mid } else { bad = mid }
        }
        let m = good;
        // Quadratic through the exact times at the middle and the end.
        let h = m / 2;
        let (mf, hf) = (m as f64, h as f64);
        let dh = self.exact_ticks(k0 + h) - x0;
        let dm = self.exact_ticks(k0 + m) - x0;
        let add = 2.0 * (dm / mf - dh / hf) / (mf - hf);
        let interval = dh / hf - add * (hf - 1.0) / 2.0;
        if interval <= 0.0 || interval + add * (mf - 1.0) <= 0.0 {
            return None;
        }
        Some(Segment {
            count: m,
            interval: round(interval * FIXED_ONE) as u64,
            add: round(add * FIXED_ONE) as i64,
        })
    }
}
