//! Watching the camera's "exposure active" strobe (spec/hardware.md,
//! "Inputs"; protocol 1.4).
//!
//! A trigger pulse only asks the camera to expose. A camera with a strobe
//! output says when it really did: the line is active for as long as its
//! sensor integrates. While [`protocol::StrobeConfig::enabled`], the
//! controller starts a watch at every pulse and reports what the line did
//! in one [`Event::Exposure`]:
//!
//! - the strobe rises (an inactive → active edge; a line already active at
//!   the pulse's rise is not an exposure of it) and falls again: the window,
//!   `ended`;
//! - it has not risen `max_delay` after the pulse's end: no window — the
//!   camera missed the trigger;
//! - it has not fallen `max_delay` after the pulse's end plus its own delay
//!   (a strobe stuck active, or a camera exposing far longer than its
//!   pulse): the window up to then, not `ended`;
//! - a new pulse (or a new strobe setting) comes first: what is known at
//!   once, so that no pulse goes unreported.
//!
//! The line is read at every input sample (the board's 200 µs poll): each
//! edge is placed at the first sample that sees it, up to one period late.
//! The watch never stops motion or latches a fault: a camera that missed a
//! frame is the host's to take again.

use protocol::{Event, StrobeWindow};

use crate::hal::TICKS_PER_US;

/// One pulse being watched.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
struct Watch {
    trigger_seq: u32,
    /// The trigger's rise, ticks.
    rise: u64,
    /// The pulse's end, ticks.
    end: u64,
    /// The strobe's rise, ticks.
    started: Option<u64>,
}

/// The strobe watch of the last pulse and the line's last sampled state.
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq)]
pub struct StrobeMonitor {
    watch: Option<Watch>,
    /// The line was active at the last sample.
    active: bool,
}

/// Ticks as whole µs, saturating.
fn us(ticks: u64) -> u32 {
    u32::try_from(ticks / TICKS_PER_US).unwrap_or(u32::MAX)
}

impl StrobeMonitor {
    /// Watch the pulse `trigger_seq` rising at `rise` for `pulse_ticks`.
    /// Returns the report of the pulse watched before it, if its watch was
    /// still running.
    pub fn start(&mut self, trigger_seq: u32, rise: u64, pulse_ticks: u64) -> Option<Event> {
        let last = self.finish(rise);
        self.watch = Some(Watch { trigger_seq, rise, end: rise + pulse_ticks, started: None });
        last
    }

    /// Whether a pulse is being watched.
    pub fn is_watching(&self) -> bool {
        self.watch.is_some()
    }

    /// End the watch at `now` with what is known (nothing if none runs).
    pub fn finish(&mut self, now: u64) -> Option<Event> {
        let w = self.watch.take()?;
        Some(report(&w, w.started.map(|s| (s, now, false))))
    }

    /// The line sampled at `now`: `active` (its level read through the
    /// configured polarity); `max_delay` ticks as configured. Returns the
    /// report when the watch ends.
    pub fn sample(&mut self, now: u64, active: bool, max_delay: u64) -> Option<Event> {
        let rose = active && !self.active;
        self.active = active;
        let w = self.watch.as_mut()?;
        let ended = match w.started {
            None if rose => {
                w.started = Some(now);
                None
            }
            None => (now >= w.end + max_delay).then_some(None),
            Some(s) if !active => Some(Some((s, now, true))),
            Some(s) => (now >= w.end + (s - w.rise) + max_delay).then_some(Some((s, now, false))),
        };
        let ended = ended?;
        let w = self.watch.take()?;
        Some(report(&w, ended))
    }
}

/// The event of watch `w` whose strobe was active from `.0` to `.1`
/// (`.2`: it fell there), or never.
fn report(w: &Watch, window: Option<(u64, u64, bool)>) -> Event {
    Event::Exposure {
        trigger_seq: w.trigger_seq,
        window: window.map(|(start, stop, ended)| StrobeWindow {
            delay_us: us(start - w.rise),
            length_us: us(stop.saturating_sub(start)),
            ended,
        }),
    }
}

#[cfg(test)]
mod tests {
    extern crate std;

    use super::*;

    const P: u64 = 200 * TICKS_PER_US;
    const MAX: u64 = 10_000 * TICKS_PER_US;

    /// Sample the line every 200 µs from `from` to `to` (exclusive) as
    /// `level(t)` says; the reports.
    fn run(
        m: &mut StrobeMonitor,
        from: u64,
        to: u64,
        level: impl Fn(u64) -> bool,
    ) -> std::vec::Vec<Event> {
        (from..to).step_by(P as usize).filter_map(|t| m.sample(t, level(t), MAX)).collect()
    }

    fn window(e: &Event) -> Option<StrobeWindow> {
        match e {
            Event::Exposure { window, .. } => *window,
            _ => panic!("{e:?}"),
        }
    }

    #[test]
    fn an_exposure_is_reported_within_a_sample_period_when_the_strobe_falls() {
        let mut m = StrobeMonitor::default();
        let rise = 1_000 * P + 37;
        assert_eq!(m.start(7, rise, 50_000 * TICKS_PER_US), None);
        // Active from 350 µs after the rise for 50 ms.
        let (a, b) = (rise + 350 * TICKS_PER_US, rise + 50_350 * TICKS_PER_US);
        let events = run(&mut m, 1_000 * P, 2_000 * P, |t| t >= a && t < b);
        assert_eq!(events.len(), 1);
        let Event::Exposure { trigger_seq: 7, window: Some(w) } = events[0] else { panic!() };
        assert!(w.ended);
        assert!((350..=550).contains(&w.delay_us), "{w:?}");
        assert!(w.length_us.abs_diff(50_000) <= 200, "{w:?}");
        assert!(!m.is_watching());
    }

    #[test]
    fn a_strobe_that_never_rises_is_a_missed_trigger_reported_when_overdue() {
        let mut m = StrobeMonitor::default();
        let pulse = 3_000 * TICKS_PER_US;
        m.start(1, 0, pulse);
        let events = run(&mut m, P, pulse + MAX, |_| false);
        assert!(events.is_empty(), "not before the bound");
        let e = m.sample(pulse + MAX, false, MAX).expect("overdue");
        assert_eq!(window(&e), None);
    }

    #[test]
    fn a_line_active_before_the_pulse_is_no_exposure_and_a_stuck_one_is_cut_short() {
        let mut m = StrobeMonitor::default();
        m.sample(0, true, MAX);
        let pulse = 3_000 * TICKS_PER_US;
        m.start(1, P / 2, pulse);
        let events = run(&mut m, P, 200 * P, |_| true);
        assert_eq!(events.iter().map(window).collect::<std::vec::Vec<_>>(), [None]);
        // Rises after the pulse, never falls: reported at end + delay + bound.
        let mut m = StrobeMonitor::default();
        m.start(2, 0, pulse);
        let start = 1_000 * TICKS_PER_US;
        let events = run(&mut m, P, 1_000 * P, |t| t >= start);
        assert_eq!(events.len(), 1);
        let w = window(&events[0]).unwrap();
        assert!(!w.ended);
        assert_eq!(w.delay_us, 1_000);
        assert_eq!(w.length_us as u64, (pulse + MAX) / TICKS_PER_US);
    }

    #[test]
    fn a_new_pulse_reports_the_last_one_at_once() {
        let mut m = StrobeMonitor::default();
        m.start(1, 0, 2_000 * TICKS_PER_US);
        assert!(run(&mut m, P, 10 * P, |t| t >= 2 * P).is_empty());
        let e = m.start(2, 10 * P, 2_000 * TICKS_PER_US).expect("the last pulse reported");
        assert_eq!(
            e,
            Event::Exposure {
                trigger_seq: 1,
                window: Some(StrobeWindow { delay_us: 400, length_us: 1_600, ended: false })
            }
        );
        assert!(m.is_watching());
        // The line still active: no edge, so the second pulse is missed.
        let e = run(&mut m, 10 * P, 200 * P, |_| true);
        assert_eq!(e.iter().map(window).collect::<std::vec::Vec<_>>(), [None]);
    }
}
