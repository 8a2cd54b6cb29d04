//! The step generator: what the step-timer interrupt runs.
//!
//! Modelled on Klipper's step queues: the planner (thread mode) compresses a
//! move into segments of `(interval, count, add)`; the interrupt only walks
//! them with O(1) integer arithmetic per step (three 64-bit adds, a compare and
//! a shift). Times are kept in fixed point, `ticks << FRAC_BITS`, so intervals
//! such as 187.5 ticks (64 000 steps/s at 12 MHz) do not drift, and the step
//! fires at `round(time)` ticks.
//!
//! The fixed-point times are relative to the move's start (`origin`), not
//! to boot: `now << FRAC_BITS` would overflow 64 bits once `now` reaches
//! 2^40 ticks (25.45 h at 12 MHz), and every step after that would be due at
//! once. Relative to its start a move has 2^40 ticks (25 h) of exact time,
//! far beyond the longest move (the full track at the slowest accepted
//! speed: 9.3 h), and the board's uptime is unbounded (2^64 ticks).
//!
//! This module owns the per-axis position counter: the position is what the
//! step pulses have done, not what was planned.

use heapless::Deque;

/// Fractional bits of the fixed-point step times.
pub const FRAC_BITS: u32 = 24;
/// One tick in fixed point.
pub const ONE_TICK: u64 = 1 << FRAC_BITS;
const HALF_TICK: u64 = ONE_TICK / 2;

/// Segments queued per axis ahead of the interrupt.
pub const QUEUE_LEN: usize = 16;

/// A run of `count` steps: the first comes `interval` after the previous step,
/// and each following interval grows by `add` (both in `ticks << FRAC_BITS`).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
#[cfg_attr(feature = "defmt", derive(defmt::Format))]
pub struct Segment {
    /// Steps in the segment (≥ 1).
    pub count: u32,
    /// Interval before the first step of the segment, fixed point.
    pub interval: u64,
    /// Change of the interval after every step, fixed point.
    pub add: i64,
}

impl Segment {
    /// Fixed-point time from the step before the segment to its last step.
    pub fn duration(&self) -> i128 {
        let m = self.count as i128;
        m * self.interval as i128 + self.add as i128 * m * (m - 1) / 2
    }
}

/// Per-axis step generator, driven by the step-timer interrupt.
#[derive(Debug)]
pub struct StepGenerator {
    queue: Deque<Segment, QUEUE_LEN>,
    count: u32,
    interval: u64,
    add: i64,
    /// Tick at which the move started: the origin of `last`.
    origin: u64,
    /// Fixed-point time of the last step since `origin`, offset by half a
    /// tick so that `>> FRAC_BITS` rounds to the nearest tick.
    last: u64,
    position: i32,
    direction: i32,
    running: bool,
}

impl Default for StepGenerator {
    fn default() -> Self {
        Self::new()
    }
}

impl StepGenerator {
    /// An idle generator at position 0.
    pub const fn new() -> Self {
        StepGenerator {
            queue: Deque::new(),
            count: 0,
            interval: 0,
            add: 0,
            origin: 0,
            last: 0,
            position: 0,
            direction: 1,
            running: false,
        }
    }

    /// Steps done so far (the axis position), in steps.
    pub fn position(&self) -> i32 {
        self.position
    }

    /// Redefine the current position (homing).
    pub fn set_position(&mut self, position: i32) {
        self.position = position;
    }

    /// Whether steps are scheduled.
    pub fn is_running(&self) -> bool {
        self.running
    }

    /// Whether nothing is scheduled or queued.
    pub fn is_idle(&self) -> bool {
        !self.running && self.queue.is_empty()
    }

    /// Restart after the interrupt ran the queue dry while segments were still
    /// coming (an underrun): the next step is timed from `now`. Returns its
    /// tick, or `None` if there is nothing to restart.
    pub fn resume(&mut self, now: u64) -> Option<u64> {
        if self.running || self.queue.is_empty() {
            return None;
        }
        let direction = self.direction;
        self.start(now, direction)
    }

    /// Free places in the segment queue.
    pub fn free(&self) -> usize {
        QUEUE_LEN - self.queue.len()
    }

    /// Direction of the current move: +1 or −1.
    pub fn direction(&self) -> i32 {
        self.direction
    }

    /// Steps scheduled but not yet done: the current segment's rest and
    /// every queued segment.
    pub fn scheduled_steps(&self) -> u32 {
        if !self.running {
            return 0;
        }
        self.queue.iter().fold(self.count, |n, s| n + s.count)
    }

    /// Queue a segment; gives it back if the queue is full.
    pub fn push(&mut self, segment: Segment) -> Result<(), Segment> {
        self.queue.push_back(segment)
    }

    /// Start a move at tick `now` in `direction` (+1/−1), its time origin being
    /// `now`. Segments must be queued first (or pushed before the first step is
    /// due). Returns the tick of the first step.
    pub fn start(&mut self, now: u64, direction: i32) -> Option<u64> {
        self.origin = now;
        self.last = HALF_TICK;
        self.direction = if direction < 0 { -1 } else { 1 };
        self.count = 0;
        self.running = true;
        self.load_next()
    }

    /// Tick of the last step (or of the move's start), rounded.
    pub fn last_step_tick(&self) -> u64 {
        self.origin.wrapping_add(self.last >> FRAC_BITS)
    }

    /// Tick of the next step, if one is scheduled.
    pub fn next_step_tick(&self) -> Option<u64> {
        (self.running && self.count > 0).then(|| self.tick(self.last + self.interval))
    }

    /// The tick of a fixed-point time since the move's start.
    fn tick(&self, fixed: u64) -> u64 {
        self.origin.wrapping_add(fixed >> FRAC_BITS)
    }

    /// **The interrupt routine**: account for the step that is due now (the
    /// caller pulses STEP) and return the tick of the next one, or `None` when
    /// the queue ran dry. O(1) integer work.
    pub fn step(&mut self) -> Option<u64> {
        if !self.running || self.count == 0 {
            return None;
        }
        self.position = self.position.wrapping_add(self.direction);
        self.last = self.last.wrapping_add(self.interval);
        self.interval = self.interval.wrapping_add_signed(self.add);
        self.count -= 1;
        if self.count > 0 {
            return Some(self.tick(self.last + self.interval));
        }
        self.load_next()
    }

    fn load_next(&mut self) -> Option<u64> {
        match self.queue.pop_front() {
            Some(seg) if seg.count > 0 => {
                self.count = seg.count;
                self.interval = seg.interval;
                self.add = seg.add;
                Some(self.tick(self.last + self.interval))
            }
            _ => {
                self.running = false;
                None
            }
        }
    }

    /// Keep only the step that is already scheduled (its time is armed in the
    /// timer) and drop everything after it; returns how many steps were
    /// dropped from the current segment and the queue (for a controlled stop).
    pub fn truncate_after_pending(&mut self) -> u32 {
        if !self.running || self.count == 0 {
            return 0;
        }
        let mut dropped = self.count - 1;
        self.count = 1;
        while let Some(seg) = self.queue.pop_front() {
            dropped += seg.count;
        }
        dropped
    }

    /// Fixed-point time of the pending step since the move's start (the
    /// origin for a plan that continues after it), if any.
    pub fn pending_step_time(&self) -> Option<u64> {
        (self.running && self.count > 0).then(|| self.last + self.interval)
    }

    /// Stop at once: drop every scheduled step.
    pub fn halt(&mut self) {
        self.running = false;
        self.count = 0;
        self.queue.clear();
    }
}
