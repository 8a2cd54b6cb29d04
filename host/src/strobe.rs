//! The camera's "exposure active" strobe, as a scan reads it (protocol 1.4,
//! docs/protocol.md §4 "Exposure strobe").
//!
//! A device whose strobe is watched ([`protocol::StrobeConfig`], set with
//! `scanner config --strobe`) reports after every pulse whether, when and
//! how long the camera exposed ([`Event::Exposure`]). A scan uses it two
//! ways:
//!
//! - **a missed trigger is known at once**: no strobe, no frame — the step
//!   is taken again without waiting out the frame timeout;
//! - **a frame that is not what the scan counts on is refused**: a camera
//!   exposing for another time than its pulse (not in trigger-width mode)
//!   makes every frame's radiance scale wrong, and one exposing past the
//!   light's end (its latency longer than the step's light margin) makes
//!   it dark at one end. Neither is cured by taking the frame again, so
//!   the scan stops and says what to set.
//!
//! The device places each of the strobe's edges up to one input sample
//! ([`protocol::INPUT_SAMPLE_US`]) after it happened; the checks allow for
//! that and refuse only what is certain.

use std::time::Duration;

use protocol::{
    Capabilities, Event, INPUT_SAMPLE_US, Reply, Request, StrobeConfig, StrobeWindow, TriggerFired,
};

use crate::link::{Device, LinkError};

/// An exposure whose strobe differs from its pulse's length by more than
/// this fraction of it (beyond the sampling's two periods) is refused.
pub const LENGTH_TOLERANCE: f64 = 0.02;

/// The device's strobe setting if it watches one (`None`: firmware before
/// protocol 1.4, a board without the input, or not enabled).
pub fn watched(dev: &mut Device) -> Result<Option<StrobeConfig>, LinkError> {
    let info = dev.info();
    if info.protocol.minor < 4 || !info.capabilities.contains(Capabilities::EXPOSURE_STROBE) {
        return Ok(None);
    }
    match dev.request(Request::GetStrobe)? {
        Reply::Strobe(s) => Ok(s.enabled.then_some(s)),
        reply => Err(LinkError::Unexpected { request: "GetStrobe", reply }),
    }
}

/// What the strobe said of the pulse `fired`.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Report {
    /// The camera exposed.
    Exposed(StrobeWindow),
    /// The strobe did not rise: the camera missed the trigger.
    Missed,
    /// No report came (lost on the link): nothing is known.
    Unknown,
}

/// Wait for the device's report on the pulse `fired` (it comes at most
/// the delay bound after the pulse's end plus the strobe's delay). The
/// wait is bounded by the protocol's longest exposure and strobe delay,
/// whatever the device says (a corrupted report would otherwise hold the
/// scan up to 2³² µs: 71 min).
pub fn report(
    dev: &mut Device,
    fired: &TriggerFired,
    strobe: &StrobeConfig,
) -> Result<Report, LinkError> {
    let seq = fired.trigger_seq;
    let exposure = fired.exposure_us.min(protocol::MAX_EXPOSURE_US) as u64;
    let delay = strobe.max_delay_us.min(protocol::MAX_STROBE_DELAY_US) as u64;
    let wait = Duration::from_micros(exposure + 2 * delay) + Duration::from_secs(1);
    let event = dev.wait_event(
        wait,
        |e| matches!(e, Event::Exposure { trigger_seq, .. } if *trigger_seq == seq),
    )?;
    Ok(match event {
        Some(Event::Exposure { window: Some(w), .. }) => Report::Exposed(w),
        Some(_) => Report::Missed,
        None => Report::Unknown,
    })
}

/// Why the frame of a pulse of `exposure_us` whose light was on
/// `light_margin_us` before and after it (`None`: a frame with the light
/// off) cannot be used as the camera's strobe window `w` says; `None` if it
/// can.
pub fn problem(w: &StrobeWindow, exposure_us: u32, light_margin_us: Option<u16>) -> Option<String> {
    let ms = |us: f64| us / 1000.0;
    let sample = INPUT_SAMPLE_US as f64;
    let (delay, length, x) = (w.delay_us as f64, w.length_us as f64, exposure_us as f64);
    if !w.ended {
        return Some(format!(
            "the camera's exposure strobe was still active {:.1} ms after its trigger rose \
             ({:.1} ms pulse): the strobe is stuck, or the camera exposes longer than its \
             trigger — set it to trigger-width (\"bulb\") exposure",
            ms(delay + length),
            ms(x)
        ));
    }
    if (length - x).abs() > 2.0 * sample + LENGTH_TOLERANCE * x {
        return Some(format!(
            "the camera exposed {:.2} ms for a {:.2} ms trigger pulse (its strobe): set it to \
             trigger-width (\"bulb\") exposure, so that the pulse sets the exposure the frames \
             are scaled by",
            ms(length),
            ms(x)
        ));
    }
    // With the light off, when the exposure ran does not matter.
    let light_margin_us = light_margin_us?;
    // Both edges are placed up to one sample late: the exposure certainly
    // ended after `delay + length - sample`.
    let light_off = x + light_margin_us as f64;
    let end = delay + length - sample;
    if end > light_off {
        let need = (delay + length - x).ceil();
        let advice = if need <= protocol::MAX_LIGHT_MARGIN_US as f64 {
            format!("give --light-margin-us {need:.0} or more")
        } else {
            format!(
                "its {:.1} ms exceed the longest light margin ({:.0} ms): shorten the \
                 camera's trigger delay",
                ms(delay),
                ms(protocol::MAX_LIGHT_MARGIN_US as f64)
            )
        };
        return Some(format!(
            "the camera exposed until {:.2} ms after its trigger rose, the light went out at \
             {:.2} ms: the camera's trigger latency ({:.2} ms by its strobe) is longer than the \
             light margin; {advice}",
            ms(delay + length),
            ms(light_off),
            ms(delay)
        ));
    }
    None
}

/// An exposure as the camera's strobe showed it, recorded with its frame
/// (docs/scan-format.md, `frames[].strobe`).
#[derive(Debug, Clone, Copy, PartialEq, Eq, serde::Serialize, serde::Deserialize)]
pub struct Exposure {
    /// From the trigger's rising edge to the strobe's, µs.
    pub delay_us: u32,
    /// How long the strobe was active, µs.
    pub length_us: u32,
}

impl Exposure {
    /// The window `w` reports, if the strobe ended within it.
    pub fn of(w: &StrobeWindow) -> Option<Exposure> {
        w.ended.then_some(Exposure { delay_us: w.delay_us, length_us: w.length_us })
    }
}

/// The strobe's exposures of a scan, summed up for its report: how late
/// the camera was and how its exposures' lengths stood against their
/// pulses, at the extremes.
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq)]
pub struct Summary {
    /// Exposures seen.
    pub exposures: usize,
    /// Shortest and longest delay, µs.
    pub delay_us: (u32, u32),
    /// Least and most the exposures lasted beyond their pulses, µs
    /// (negative: shorter).
    pub excess_us: (i64, i64),
}

impl Summary {
    /// Count the exposure `e` of a pulse of `pulse_us`.
    pub fn add(&mut self, e: &Exposure, pulse_us: u32) {
        let excess = e.length_us as i64 - pulse_us as i64;
        if self.exposures == 0 {
            self.delay_us = (e.delay_us, e.delay_us);
            self.excess_us = (excess, excess);
        } else {
            self.delay_us = (self.delay_us.0.min(e.delay_us), self.delay_us.1.max(e.delay_us));
            self.excess_us = (self.excess_us.0.min(excess), self.excess_us.1.max(excess));
        }
        self.exposures += 1;
    }

    /// In words, with the light's margin after the pulse (what the latest
    /// exposure's end may reach); `None` when no exposure was seen.
    pub fn describe(&self, light_margin_us: u16) -> Option<String> {
        if self.exposures == 0 {
            return None;
        }
        let ms = |us: f64| us / 1000.0;
        // "a–b", or "a" when both read the same.
        let range = |a: String, b: String, sep: &str| if a == b { a } else { a + sep + &b };
        let latest_end = self.delay_us.1 as i64 + self.excess_us.1;
        Some(format!(
            "camera strobe over {} exposures: {} ms after the trigger, {} ms against the pulse \
             (each edge to {:.1} ms); ends up to {:.1} ms after the pulse, the light {:.1} ms",
            self.exposures,
            range(
                format!("{:.1}", ms(self.delay_us.0 as f64)),
                format!("{:.1}", ms(self.delay_us.1 as f64)),
                "–"
            ),
            range(
                format!("{:+.1}", ms(self.excess_us.0 as f64)),
                format!("{:+.1}", ms(self.excess_us.1 as f64)),
                "…"
            ),
            ms(INPUT_SAMPLE_US as f64),
            ms(latest_end as f64),
            ms(light_margin_us as f64),
        ))
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn window(delay_us: u32, length_us: u32) -> StrobeWindow {
        StrobeWindow { delay_us, length_us, ended: true }
    }

    #[test]
    fn a_summary_keeps_the_extremes_and_says_how_close_the_light_margin_is() {
        let mut s = Summary::default();
        assert_eq!(s.describe(0), None);
        s.add(&Exposure { delay_us: 1_000, length_us: 50_000 }, 50_000);
        s.add(&Exposure { delay_us: 1_200, length_us: 10_200 }, 10_000);
        s.add(&Exposure { delay_us: 1_000, length_us: 1_000 }, 1_200);
        assert_eq!(s, Summary { exposures: 3, delay_us: (1_000, 1_200), excess_us: (-200, 200) });
        assert_eq!(
            s.describe(1_500).unwrap(),
            "camera strobe over 3 exposures: 1.0–1.2 ms after the trigger, -0.2…+0.2 ms against \
             the pulse (each edge to 0.2 ms); ends up to 1.4 ms after the pulse, the light 1.5 ms"
        );
        let mut one = Summary::default();
        one.add(&Exposure { delay_us: 1_100, length_us: 50_000 }, 50_000);
        assert!(one.describe(0).unwrap().contains(": 1.1 ms after the trigger, +0.0 ms against"));
        let stuck = StrobeWindow { delay_us: 100, length_us: 60_000, ended: false };
        assert_eq!(Exposure::of(&stuck), None);
    }

    #[test]
    fn an_exposure_within_its_pulse_and_light_passes_at_the_sampling_limits() {
        // A camera with no latency, its edges each seen up to a sample late.
        assert_eq!(problem(&window(0, 50_000), 50_000, Some(0)), None);
        assert_eq!(problem(&window(199, 50_000), 50_000, Some(0)), None);
        assert_eq!(problem(&window(0, 50_199), 50_000, Some(0)), None);
        // A 300 µs latency under a 400 µs margin.
        assert_eq!(problem(&window(400, 50_000), 50_000, Some(400)), None);
    }

    #[test]
    fn a_latency_beyond_the_light_margin_is_refused_with_the_margin_it_needs() {
        let why = problem(&window(1_000, 50_000), 50_000, Some(200)).unwrap();
        assert!(why.contains("--light-margin-us 1000 or more"), "{why}");
        let why = problem(&window(12_000, 50_000), 50_000, Some(0)).unwrap();
        assert!(why.contains("exceed the longest light margin"), "{why}");
    }

    #[test]
    fn an_exposure_set_on_the_camera_instead_of_by_the_pulse_is_refused() {
        let why = problem(&window(100, 20_000), 50_000, Some(0)).unwrap();
        assert!(why.contains("exposed 20.00 ms for a 50.00 ms trigger pulse"), "{why}");
        // 2 % + two samples: 1.4 ms on 50 ms.
        assert_eq!(problem(&window(0, 48_700), 50_000, Some(0)), None);
        assert!(problem(&window(0, 48_500), 50_000, Some(0)).is_some());
        // With the light off (a dark frame) the latency does not matter,
        // the exposure's length does.
        assert_eq!(problem(&window(12_000, 50_000), 50_000, None), None);
        assert!(problem(&window(100, 20_000), 50_000, None).is_some());
        let stuck = StrobeWindow { delay_us: 100, length_us: 60_000, ended: false };
        assert!(problem(&stuck, 50_000, Some(0)).unwrap().contains("still active 60.1 ms"));
    }
}
