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
/// the delay bound after the pulse's end plus the strobe's delay).
pub fn report(
    dev: &mut Device,
    fired: &TriggerFired,
    strobe: &StrobeConfig,
) -> Result<Report, LinkError> {
    let seq = fired.trigger_seq;
    let wait = Duration::from_micros(fired.exposure_us as u64 + 2 * strobe.max_delay_us as u64)
        + Duration::from_secs(1);
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

#[cfg(test)]
mod tests {
    use super::*;

    fn window(delay_us: u32, length_us: u32) -> StrobeWindow {
        StrobeWindow { delay_us, length_us, ended: true }
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
