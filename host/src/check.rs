//! `scanner check`: a scanner's acceptance run — what a hardware-in-the-loop
//! test of a built scanner asks, in one command, each answer a line
//! (README, "Commissioning a scanner").
//!
//! The checks run in order, and one that needs an earlier one skips when
//! that failed:
//!
//! 1. **link** — the handshake, and the round trip of status requests;
//! 2. **faults** — none latched, the emergency stop closed, the drivers
//!    quiet (their inputs, protocol ≥ 1.2);
//! 3. **light** — switched on and off, as the status reads back;
//! 4. **camera** — a frame with the light off for a bare trigger, of the
//!    geometry's sensor size, and on a device that watches the exposure
//!    strobe, exposed for the pulse's length;
//! 5. **homing** — every axis homed, sent far along its travel and homed
//!    again, `homings` times ([`scan::homing_repeatability`]): its count at
//!    its switch within [`protocol::POSITION_TOLERANCE_STEPS`];
//! 6. **mirror table** — the device's table is the geometry's (read only:
//!    `scanner setup` writes it);
//! 7. **mirrors** — every entry of the device's table visited, then homed:
//!    no step lost on the way;
//! 8. **capture** — with the table the geometry's, capture steps at the
//!    first, middle and last mirror whose reflection faces a view, and the
//!    last mirror ([`capture_mirrors`]): each frame shows the sample on the holder lit
//!    (a view [`LIT_CODES`] above the frame with the light off), the
//!    strobe's timing within the light; with a glossy target on the holder
//!    its highlight in the view the lit mirror's reflection faces (else the
//!    beam went to another mirror: [`facing_views`], [`HIGHLIGHT_OVER_NEXT`]).
//!
//! Nothing is written to the device (no table, no setting): the axes move
//! and home, the light switches, the trigger fires.

use std::time::{Duration, Instant};

use protocol::{AxisSet, LightState, Request};
use scanner_geometry::ScannerGeometry;

use crate::camera::{Camera, ScanCamera};
use crate::link::{Device, LinkError};
use crate::scan::{self, ScanError, ScanOptions, ScanReport};

/// A sample counts as lit when one of its views' level (the median over
/// its sample points) is this many ADC codes above the same view's in the
/// frame with the light off: 13 × the read noise of a
/// typical sensor (the dark frame's hot-pixel threshold, docs/scan-format.md
/// "Sensor defects"), so that no dark frame passes and any sample but a
/// black one at a short exposure does.
pub const LIT_CODES: f64 = 16.0;

/// Status requests whose round trip the link check times.
pub const ROUND_TRIPS: usize = 20;

/// What to check with.
#[derive(Debug, Clone)]
pub struct CheckOptions {
    /// The scanner's geometry (its mirror table, its sensor, where the
    /// sample appears in the frames).
    pub geometry: ScannerGeometry,
    /// Homing cycles of the homing check.
    pub homings: usize,
    /// Capture at every mirror [`capture_mirrors`] may choose, not three.
    pub capture_all: bool,
    /// The target is glossy: a step at a mirror facing a view must show a
    /// highlight (views alike fail).
    pub glossy: bool,
    /// The capture steps' exposure, settle, light and frame timeout (as a
    /// scan's; `attempts` retakes a missed frame).
    pub scan: ScanOptions,
}

/// A check's result.
#[derive(Debug, Clone, Copy, PartialEq, Eq, serde::Serialize, serde::Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum Verdict {
    /// It passed.
    Pass,
    /// It failed: the detail says what and what to do.
    Fail,
    /// It could not run (a check it needs failed, or no camera).
    Skip,
}

impl Verdict {
    /// As printed: PASS, FAIL, SKIP.
    pub fn word(self) -> &'static str {
        match self {
            Verdict::Pass => "PASS",
            Verdict::Fail => "FAIL",
            Verdict::Skip => "SKIP",
        }
    }
}

/// One check's outcome.
#[derive(Debug, Clone, PartialEq, serde::Serialize)]
pub struct Outcome {
    /// The check, e.g. "homing".
    pub name: &'static str,
    /// Passed, failed or skipped.
    pub verdict: Verdict,
    /// What was measured, or why it failed or was skipped.
    pub detail: String,
    /// How long it took, s (0 when skipped).
    pub seconds: f64,
}

/// The checks, in the order they run.
pub const CHECKS: [&str; 8] =
    ["link", "faults", "light", "camera", "homing", "mirror table", "mirrors", "capture"];

/// Run every check on `dev` (and `camera`, if there is one), telling
/// `seen` each outcome as it comes; all outcomes, in [`CHECKS`] order.
pub fn run(
    dev: &mut Device,
    camera: Option<&mut dyn Camera>,
    o: &CheckOptions,
    seen: &mut dyn FnMut(&Outcome),
) -> Vec<Outcome> {
    let mut out: Vec<Outcome> = Vec::new();
    let mut say = |name: &'static str, verdict: Verdict, detail: String, took: Duration| {
        let outcome = Outcome { name, verdict, detail, seconds: took.as_secs_f64() };
        seen(&outcome);
        out.push(outcome);
        verdict == Verdict::Pass
    };
    // A link that failed (the device gone, silent or reset) fails the
    // check it happened in; the rest are skipped. A refused request fails
    // only its check. A board that reset (a new boot id: the watchdog, a
    // brown-out) fails the check it reset in, whatever that check made of
    // it, and ends the run: its homing and state are gone.
    let boot_id = dev.info().boot_id;
    let mut gone: Option<String> = None;
    let mut run_one = |dev: &mut Device,
                       name: &'static str,
                       needs: &[(&str, bool)],
                       check: &mut dyn FnMut(&mut Device) -> Checked|
     -> bool {
        if let Some(why) = &gone {
            return say(name, Verdict::Skip, format!("after {why}"), Duration::ZERO);
        }
        if let Some((what, _)) = needs.iter().find(|(_, ok)| !ok) {
            return say(name, Verdict::Skip, format!("needs {what}"), Duration::ZERO);
        }
        let started = Instant::now();
        let result = check(dev);
        let took = started.elapsed();
        let now = dev.info().boot_id;
        if now != boot_id {
            let why = format!("the board reset (boot id {boot_id:08x} → {now:08x})");
            let detail = match &result {
                Ok(Ok(d)) | Ok(Err(d)) => d.clone(),
                Err(e) => e.to_string(),
            };
            // What the check made of it, unless that was the reset itself.
            let said =
                if detail.contains("reset") { String::new() } else { format!(" ({detail})") };
            let fail = format!(
                "{why} during this check: a watchdog reset or a brown-out — check the supply \
                 under load{said}"
            );
            gone = Some(why);
            return say(name, Verdict::Fail, fail, took);
        }
        match result {
            Ok(Ok(detail)) => say(name, Verdict::Pass, detail, took),
            Ok(Err(why)) => say(name, Verdict::Fail, why, took),
            Err(e) => {
                if let ScanError::Link(
                    LinkError::NoDevice(_) | LinkError::Timeout { .. } | LinkError::Reset { .. },
                ) = e
                {
                    gone = Some(format!("the link failed ({e})"));
                }
                say(name, Verdict::Fail, e.to_string(), took)
            }
        }
    };
    let link = run_one(dev, "link", &[], &mut link);
    let faults = run_one(dev, "faults", &[("link", link)], &mut faults);
    let light = run_one(dev, "light", &[("faults", faults)], &mut |d| light(d, &o.scan));
    // Without a camera its checks are skipped (never run).
    let no_camera = [("a camera (--camera)", false)];
    let never = &mut |_: &mut Device| -> Checked { Ok(Err(String::new())) };
    let mut camera = camera.map(|c| ScanCamera::new(c, &o.geometry));
    let mut dark = None;
    let seen_dark = match camera.as_mut() {
        None => run_one(dev, "camera", &no_camera, never),
        Some(camera) => run_one(dev, "camera", &[("faults", faults)], &mut |d| {
            Ok(dark_frame(d, camera, o)?.map(|(frame, detail)| {
                dark = Some(frame);
                detail
            }))
        }),
    };
    let homing = run_one(dev, "homing", &[("faults", faults)], &mut |d| homing(d, o.homings));
    let table =
        run_one(dev, "mirror table", &[("link", link)], &mut |d| mirror_table(d, &o.geometry));
    let mirrors = run_one(dev, "mirrors", &[("homing", homing)], &mut mirrors);
    match (camera.as_mut(), dark.as_ref()) {
        (Some(camera), Some(dark)) => {
            // The table as the geometry's: a capture step that must
            // recover (as a scan's does) then writes nothing to the device.
            let needs = [("mirror table", table), ("mirrors", mirrors), ("light", light)];
            run_one(dev, "capture", &needs, &mut |d| capture(d, camera, o, dark))
        }
        (None, _) => run_one(dev, "capture", &no_camera, never),
        (Some(_), None) => run_one(dev, "capture", &[("camera", seen_dark)], never),
    };
    out
}

/// A run's record, as `scanner check --report` writes it (docs/check-report.md).
#[derive(Debug, Clone, serde::Serialize)]
pub struct Report<'a> {
    /// "scanner-check".
    pub format: &'static str,
    /// 1.
    pub version: u32,
    /// When the run ended, s since 1970 (UTC).
    pub unix_time_s: u64,
    /// The device: its id (hex), firmware, protocol, board, boot id (hex).
    pub device: ReportDevice,
    /// Every check, in [`CHECKS`] order.
    pub checks: &'a [Outcome],
    /// How many passed, failed, were skipped.
    pub passed: usize,
    /// Failed.
    pub failed: usize,
    /// Skipped.
    pub skipped: usize,
}

/// The device a report is of.
#[derive(Debug, Clone, serde::Serialize)]
pub struct ReportDevice {
    /// Its unique id, hex.
    pub device_id: String,
    /// Firmware version.
    pub firmware: String,
    /// Protocol version.
    pub protocol: String,
    /// Board id.
    pub board: u16,
    /// Boot id at the run's start, hex.
    pub boot_id: String,
}

impl<'a> Report<'a> {
    /// The record of `checks`, run on the device `info` describes.
    pub fn new(info: &protocol::DeviceInfo, checks: &'a [Outcome]) -> Report<'a> {
        let count = |v| checks.iter().filter(|o| o.verdict == v).count();
        Report {
            format: "scanner-check",
            version: 1,
            unix_time_s: std::time::SystemTime::now()
                .duration_since(std::time::UNIX_EPOCH)
                .map_or(0, |d| d.as_secs()),
            device: ReportDevice {
                device_id: scan::hex(&info.device_id),
                firmware: info.firmware.to_string(),
                protocol: info.protocol.to_string(),
                board: info.board,
                boot_id: format!("{:08x}", info.boot_id),
            },
            checks,
            passed: count(Verdict::Pass),
            failed: count(Verdict::Fail),
            skipped: count(Verdict::Skip),
        }
    }
}

/// Error-typed results: `Ok(Ok(detail))` passed, `Ok(Err(why))` failed.
type Checked = Result<Result<String, String>, ScanError>;

fn link(dev: &mut Device) -> Checked {
    let info = *dev.info();
    let before = dev.stats;
    let mut times = Vec::with_capacity(ROUND_TRIPS);
    for _ in 0..ROUND_TRIPS {
        let t = Instant::now();
        dev.status()?;
        times.push(t.elapsed());
    }
    times.sort_unstable();
    let retransmitted = dev.stats.retransmissions - before.retransmissions;
    let bad = dev.stats.bad_frames - before.bad_frames;
    let detail = format!(
        "device {}, firmware {}, protocol {}, board {:#06x}; {ROUND_TRIPS} status round trips: \
         median {:.1} ms, longest {:.1} ms",
        scan::hex(&info.device_id),
        info.firmware,
        info.protocol,
        info.board,
        ms(times[ROUND_TRIPS / 2]),
        ms(times[ROUND_TRIPS - 1]),
    );
    if retransmitted + bad > 0 {
        return Ok(Err(format!(
            "{detail}; {retransmitted} retransmissions and {bad} bad frames on a quiet link: \
             check the cable, its shield and the USB hub"
        )));
    }
    Ok(Ok(detail))
}

fn faults(dev: &mut Device) -> Checked {
    let status = dev.status()?;
    let mut wrong = Vec::new();
    if !status.faults.is_empty() {
        wrong.push(format!(
            "faults latched: {} (`scanner clear` clears them once their cause is gone)",
            scan::fault_list(status.faults)
        ));
    }
    let mut seen = "no fault latched".to_string();
    if dev.info().protocol.minor >= 2 {
        let inputs = match dev.request(Request::GetInputs)? {
            protocol::Reply::Inputs(i) => i,
            reply => return Err(LinkError::Unexpected { request: "GetInputs", reply }.into()),
        };
        if inputs.estop_open {
            wrong.push("the emergency stop is open".into());
        }
        if inputs.driver_fault {
            wrong.push(
                "a driver reports a fault (or its line's polarity is set the wrong way round: \
                 `scanner config --driver-fault`)"
                    .into(),
            );
        }
        seen += ", the emergency stop closed, the drivers quiet";
    }
    if wrong.is_empty() { Ok(Ok(seen)) } else { Ok(Err(wrong.join("; "))) }
}

fn homing(dev: &mut Device, cycles: usize) -> Checked {
    let cycles = scan::homing_repeatability(dev, AxisSet::ALL, cycles, &mut |_, _| {})?;
    let tolerance = protocol::POSITION_TOLERANCE_STEPS;
    let axes = scan::repeatability(&cycles, AxisSet::ALL);
    let words: Vec<String> = axes
        .iter()
        .map(|r| match r.range {
            // Not measured in a cycle another axis' lost steps stopped.
            Some((lo, hi)) if r.measured < cycles.len() => {
                format!("{} {lo:+}…{hi:+} (measured in {} of them)", r.axis.name(), r.measured)
            }
            Some((lo, hi)) => format!("{} {lo:+}…{hi:+}", r.axis.name()),
            None => format!("{} not measured", r.axis.name()),
        })
        .collect();
    let detail = format!(
        "count at the switch after {} homings, steps: {} (tolerance ±{tolerance})",
        cycles.len(),
        words.join(", ")
    );
    let lost: Vec<&str> = axes.iter().filter(|r| !r.kept).map(|r| r.axis.name()).collect();
    if lost.is_empty() {
        return Ok(Ok(detail));
    }
    Ok(Err(format!(
        "{detail}: {} lost steps (or was never measured) — lower its v_max or a_max (`scanner \
         axes`), or check the motor's current, its coupling and what it drives",
        lost.join(", ")
    )))
}

fn mirror_table(dev: &mut Device, geometry: &ScannerGeometry) -> Checked {
    let axes = scan::axis_configs(dev)?;
    let table = scan::mirror_table(geometry, &axes)?;
    let count = dev.info().mirror_count as usize;
    let mut differ = Vec::new();
    for (l, position) in table.iter().enumerate() {
        if l >= count || scan::mirror_entry(dev, l as u8)? != Some(*position) {
            differ.push(l);
        }
    }
    if differ.is_empty() && count == table.len() {
        return Ok(Ok(format!("{count} entries, the geometry's for the device's axes")));
    }
    let what = if count == 0 {
        format!("the device's table is empty, the geometry has {} mirrors", table.len())
    } else if differ.is_empty() {
        format!("the device has {count} entries, the geometry {}", table.len())
    } else {
        format!("{} of {} entries differ from the geometry's", scan::mirror_list(&differ), count)
    };
    Ok(Err(format!("{what}: `scanner setup --geometry` writes the geometry's")))
}

fn mirrors(dev: &mut Device) -> Checked {
    let count = dev.info().mirror_count;
    let mut visited = Vec::new();
    let mut longest = Duration::ZERO;
    let started = Instant::now();
    for l in 0..count {
        if scan::mirror_entry(dev, l)?.is_none() {
            continue;
        }
        let t = Instant::now();
        dev.clear_events();
        dev.command(Request::GoToMirror { mirror: l })?;
        match scan::wait_motion_end(dev, Duration::from_secs(120))? {
            Some(scan::MotionEnd::Reported {
                outcome: protocol::MotionOutcome::Completed, ..
            }) => {}
            Some(scan::MotionEnd::Unreported(s)) if s.faults.is_empty() => {}
            Some(scan::MotionEnd::Reported { outcome, .. }) => {
                return Ok(Err(format!("the move to mirror {l}: {outcome}")));
            }
            Some(scan::MotionEnd::Unreported(s)) => {
                return Ok(Err(format!(
                    "the move to mirror {l} stopped: {}",
                    scan::fault_list(s.faults)
                )));
            }
            None => return Ok(Err(format!("the move to mirror {l} did not end within 120 s"))),
        }
        longest = longest.max(t.elapsed());
        visited.push(l as usize);
    }
    if visited.is_empty() {
        return Ok(Err("the device's mirror table is empty: `scanner setup` writes it".into()));
    }
    let moved = started.elapsed();
    // Homing measures each axis' count against its switch.
    let mut error_steps = [None; 3];
    for e in scan::home_axes(dev, AxisSet::ALL)? {
        if let protocol::Event::PositionChecked { axis, error_steps: error } = e {
            error_steps[axis.index()] = Some(error);
        }
    }
    let words: Vec<String> = protocol::Axis::ALL
        .iter()
        .map(|a| match error_steps[a.index()] {
            Some(e) => format!("{} {e:+}", a.name()),
            None => format!("{} not measured", a.name()),
        })
        .collect();
    let detail = format!(
        "{} visited in {:.1} s (the longest move {:.1} s); homed after: {} steps",
        scan::mirror_list(&visited),
        moved.as_secs_f64(),
        longest.as_secs_f64(),
        words.join(", ")
    );
    if error_steps.iter().all(|e| e.is_some_and(scan::within_tolerance)) {
        Ok(Ok(detail))
    } else {
        Ok(Err(format!(
            "{detail}: steps were lost on the way (`scanner home --repeat` narrows it)"
        )))
    }
}

fn light(dev: &mut Device, o: &ScanOptions) -> Checked {
    let mut read = Vec::new();
    for on in [true, false] {
        dev.command(Request::SetLight(LightState { on, duty_permille: o.light_duty_permille }))?;
        let light = dev.status()?.light;
        read.push(light);
        if light.on != on {
            return Ok(Err(format!("switched {}, the status reads {light:?}", onoff(on))));
        }
    }
    Ok(Ok(format!("on at {} ‰ and off again, as the status reads", read[0].duty_permille)))
}

fn onoff(on: bool) -> &'static str {
    if on { "on" } else { "off" }
}

/// The frame with the light off, and what the check says of it.
fn dark_frame(
    dev: &mut Device,
    camera: &mut dyn Camera,
    o: &CheckOptions,
) -> Result<Result<(crate::camera::Frame, String), String>, ScanError> {
    let mut report = ScanReport::default();
    let dark =
        scan::DarkFrame { geometry: &o.geometry, opts: &o.scan, exposure_us: o.scan.exposure_us };
    let t = Instant::now();
    let (frame, window) = match dark.take(dev, camera, &mut report) {
        Ok(Ok(taken)) => taken,
        Ok(Err(why)) => return Ok(Err(format!("a bare trigger with the light off: {why}"))),
        // Another size or unit, or a strobe that says the camera exposes
        // otherwise than its pulse: what to set is in the words.
        Err(ScanError::Conflict(why)) => return Ok(Err(why)),
        Err(e) => return Err(e),
    };
    let took = t.elapsed();
    let max_code = o.geometry.sensor.max_code();
    let black = crate::defects::black_level_codes(&frame, max_code);
    let mut detail = format!(
        "a {:.1} ms frame with the light off, {}×{}, in {:.2} s from the trigger's request; its \
         median {black} codes",
        o.scan.exposure_us as f64 / 1000.0,
        frame.width,
        frame.height,
        took.as_secs_f64()
    );
    if black > crate::defects::DARK_MEDIAN_CODES {
        detail += &format!(
            " — a black level: scan with --black-level {black} (or auto), or have the camera's \
             capture program subtract it"
        );
    }
    if let Some(w) = window {
        detail += &format!(
            "; its exposure strobe {:.1} ms after the trigger, as long as the pulse",
            w.delay_us as f64 / 1000.0
        );
    } else if crate::strobe::watched(dev)?.is_some() {
        detail += "; its exposure strobe as long as the pulse";
    }
    Ok(Ok((frame, detail)))
}

/// The level of the sample's views in `frame` (full scale 1) and the
/// share of their values saturated.
fn sample_level(frame: &crate::camera::Frame, geometry: &ScannerGeometry) -> Option<(f64, f64)> {
    let pixels = crate::exposure::sample_pixels(frame, geometry);
    let none = crate::defects::DefectMap::new(&[], frame.width, frame.height);
    let mut values = crate::exposure::sample_values(&pixels, &none);
    if values.is_empty() {
        return None;
    }
    let saturated = values.iter().filter(|&&v| v >= crate::exposure::SATURATED).count();
    let (body, _, _) = crate::exposure::measure(&mut values);
    Some((body, saturated as f64 / values.len() as f64))
}

/// A light's mirror reflection counts as facing a view when it lies within
/// this of the view's direction (the default scanner's first and third
/// rings: 1.5–1.6°; the others ≈ 11°): a glossy target's highlight then
/// shows in that view alone.
pub const FACING_DEG: f64 = 3.0;

/// A view shows a glossy target's highlight when its level above the dark
/// frame is at least this many times the next brightest view's (and
/// [`HIGHLIGHT_OVER_MEDIAN`] × the views' median): a diffuse sample's
/// views lie within a factor of two of each other (mirror reflectance,
/// vignetting, cos θ).
pub const HIGHLIGHT_OVER_NEXT: f64 = 4.0;

/// See [`HIGHLIGHT_OVER_NEXT`].
pub const HIGHLIGHT_OVER_MEDIAN: f64 = 8.0;

/// For every light, the view nearest its mirror reflection (about the
/// holder's normal) and the angle between them, degrees, by the nominal
/// directions: where a glossy target's highlight (or its tail) shows.
pub fn reflection_views(g: &ScannerGeometry) -> Vec<Option<(usize, f64)>> {
    (0..g.mirrors.len())
        .map(|l| {
            let light = g.light_direction(l).ok()?;
            let reflected = scanner_geometry::DVec3::new(-light.x, -light.y, light.z);
            (0..g.mirrors.len())
                .filter_map(|j| {
                    let a = g.mirror_direction(j)?.dot(reflected).clamp(-1.0, 1.0).acos();
                    Some((j, a.to_degrees()))
                })
                .min_by(|a, b| a.1.total_cmp(&b.1))
        })
        .collect()
}

/// For every light, the view its mirror reflection faces within
/// [`FACING_DEG`] ([`reflection_views`]).
pub fn facing_views(g: &ScannerGeometry) -> Vec<Option<usize>> {
    facing_of(&reflection_views(g))
}

/// [`facing_views`] from the lights' [`reflection_views`].
fn facing_of(reflections: &[Option<(usize, f64)>]) -> Vec<Option<usize>> {
    reflections.iter().map(|r| r.filter(|(_, a)| *a <= FACING_DEG).map(|(j, _)| j)).collect()
}

/// The capture check's mirrors among `count`: the first, middle and last
/// (`all`: every one) of those whose reflection faces a view (a glossy
/// target then tells where the beam went), else of all; and the last
/// mirror (the outermost ring, the axes' farthest reach), last.
pub fn capture_mirrors(count: usize, facing: &[Option<usize>], all: bool) -> Vec<usize> {
    let candidates: Vec<usize> =
        (0..count).filter(|&l| facing.get(l).is_some_and(Option::is_some)).collect();
    let from: Vec<usize> = if candidates.is_empty() { (0..count).collect() } else { candidates };
    let mut chosen: Vec<usize> = if all {
        from.clone()
    } else {
        [0, from.len() / 2, from.len().saturating_sub(1)]
            .iter()
            .filter_map(|&i| from.get(i).copied())
            .collect()
    };
    chosen.dedup();
    if let Some(last) = count.checked_sub(1)
        && !chosen.contains(&last)
    {
        chosen.push(last);
    }
    chosen
}

/// Each view's level (the median over its sample points of their mean
/// channel, in full scale); `None` for a view outside the frame.
fn view_levels(frame: &crate::camera::Frame, g: &ScannerGeometry) -> Vec<Option<f64>> {
    (0..g.mirrors.len())
        .map(|j| {
            crate::stats::median(
                crate::exposure::view_pixels(frame, g, j)
                    .iter()
                    .map(|(_, c)| c.iter().map(|&x| x as f64).sum::<f64>() / 3.0)
                    .collect(),
            )
        })
        .collect()
}

/// The view showing a highlight among views `codes` above the dark frame
/// (view, codes), if one outshines the rest ([`HIGHLIGHT_OVER_NEXT`]).
fn highlight(codes: &[(usize, f64)]) -> Option<usize> {
    let mut sorted = codes.to_vec();
    sorted.sort_by(|a, b| b.1.total_cmp(&a.1));
    let (&(view, top), rest) = sorted.split_first()?;
    let next = rest.first().map_or(0.0, |r| r.1).max(1.0);
    let median = sorted[sorted.len() / 2].1.max(1.0);
    (top >= LIT_CODES && top >= HIGHLIGHT_OVER_NEXT * next && top >= HIGHLIGHT_OVER_MEDIAN * median)
        .then_some(view)
}

/// What a capture step's frame shows of where the beam went.
#[derive(Debug, Clone, Copy, PartialEq)]
enum Beam {
    /// The views alike (a diffuse sample): their level, full scale.
    Alike(f64),
    /// A highlight in `view`, the one nearest the lit mirror's reflection.
    Facing(usize),
    /// A highlight in `view`, not the one nearest the lit mirror's
    /// reflection (`expected`, if any): the light `from` faces it, if one
    /// does.
    Elsewhere { view: usize, expected: Option<usize>, from: Option<usize> },
}

/// The views a glossy target's highlight shows in: for every light, the
/// one it faces ([`facing_views`]), and the one nearest its reflection.
struct Reflections {
    facing: Vec<Option<usize>>,
    nearest: Vec<Option<usize>>,
}

impl Reflections {
    fn of(g: &ScannerGeometry) -> Reflections {
        let views = reflection_views(g);
        let nearest = views.iter().map(|r| r.map(|(j, _)| j)).collect();
        Reflections { facing: facing_of(&views), nearest }
    }
}

/// Where the beam of light `l` went, as `frame` (against `dark`'s views)
/// shows it; `None` when no view is [`LIT_CODES`] above the dark frame.
fn beam_of(
    l: usize,
    views: &[Option<f64>],
    dark: &[Option<f64>],
    r: &Reflections,
    max_code: f64,
    level: f64,
) -> Option<Beam> {
    let codes: Vec<(usize, f64)> = views
        .iter()
        .zip(dark)
        .enumerate()
        .filter_map(|(j, (v, d))| Some((j, codes_above((*v)?, (*d)?, max_code))))
        .collect();
    if codes.iter().all(|&(_, c)| c < LIT_CODES) {
        return None;
    }
    let Some(view) = highlight(&codes) else { return Some(Beam::Alike(level)) };
    let expected = r.nearest.get(l).copied().flatten();
    if expected == Some(view) {
        return Some(Beam::Facing(view));
    }
    let from = r.facing.iter().position(|f| *f == Some(view));
    Some(Beam::Elsewhere { view, expected, from })
}

/// Why the step at mirror `l` showed no view lit.
fn unlit(l: usize, facing: &[Option<usize>]) -> String {
    // A glossy target lit through a mirror whose reflection faces no view
    // shows its highlight nowhere.
    let glossy = match facing.get(l) {
        Some(Some(_)) => "",
        _ => {
            "; a glossy target lit through this mirror shows its highlight in no view: check \
             with a diffuse one"
        }
    };
    format!(
        "mirror {l}: no view of the sample {LIT_CODES} codes above the frame with the light off: \
         the beam does not reach the sample (the mirror table, the light, the fold mirror), or no \
         sample is on the holder{glossy}"
    )
}

fn capture(
    dev: &mut Device,
    camera: &mut dyn Camera,
    o: &CheckOptions,
    dark: &crate::camera::Frame,
) -> Checked {
    let count = dev.info().mirror_count as usize;
    let reflections = Reflections::of(&o.geometry);
    let facing = &reflections.facing;
    let mirrors = capture_mirrors(count, facing, o.capture_all);
    let max_code = o.geometry.sensor.max_code();
    let dark_views = view_levels(dark, &o.geometry);
    if dark_views.iter().all(Option::is_none) {
        return Ok(Err("the geometry projects the sample outside the camera's frames".into()));
    }
    let mut report = ScanReport::default();
    let (mut alike, mut facing_seen, mut wrong) = (Vec::new(), Vec::new(), Vec::new());
    // Mirrors a glossy target (a highlight seen at an earlier step) shows
    // nothing through: their reflection faces no view.
    let mut unjudged = Vec::new();
    // Steps with `glossy` whose views were alike.
    let mut flat = Vec::new();
    for &l in &mirrors {
        let ((frame, _, _, exposure), _) = scan::capture_with_retries(
            dev,
            camera,
            &o.geometry,
            l,
            &o.scan,
            &mut report,
            &mut scan::Quiet,
        )?;
        if let Some(e) = &exposure {
            report.strobe.add(e, o.scan.exposure_us);
        }
        // The same geometry and frame size as the dark frame's: it has views.
        let (level, saturated) = sample_level(&frame, &o.geometry).unwrap_or((0.0, 0.0));
        let views = view_levels(&frame, &o.geometry);
        let glossy = !facing_seen.is_empty() || !wrong.is_empty();
        match beam_of(l, &views, &dark_views, &reflections, max_code, level) {
            None if glossy && facing.get(l).is_some_and(Option::is_none) => unjudged.push(l),
            None => return Ok(Err(unlit(l, facing))),
            Some(Beam::Alike(level)) if o.glossy && facing.get(l).is_some_and(Option::is_some) => {
                flat.push(format!("mirror {l} (views at {:.1} %)", 100.0 * level))
            }
            Some(Beam::Alike(level)) => {
                alike.push(format!("mirror {l} at {:.1} %{}", 100.0 * level, saturation(saturated)))
            }
            Some(Beam::Facing(view)) => facing_seen.push(format!("mirror {l} in view {view}")),
            Some(Beam::Elsewhere { view, expected, from }) => wrong.push(format!(
                "mirror {l}: the highlight shows in view {view}{}{}",
                match from {
                    Some(k) => format!(", where mirror {k}'s light is reflected"),
                    None => String::new(),
                },
                match expected {
                    Some(e) => format!(", not in view {e}"),
                    None => String::new(),
                }
            )),
        }
    }
    if !wrong.is_empty() {
        return Ok(Err(format!(
            "{}: the beam lit another mirror than the table's — the axes' home positions or \
             steps per unit (`scanner move --mirror N` and look where the beam lands; \
             docs/axis-config.md)",
            wrong.join("; ")
        )));
    }
    if !flat.is_empty() {
        return Ok(Err(format!(
            "{}: no highlight, the views alike, though --glossy says the target is glossy: a \
             diffuse sample on the holder, or a beam that is not collimated (the source, the fold \
             mirror)",
            flat.join(", ")
        )));
    }
    let mut parts = Vec::new();
    if !facing_seen.is_empty() {
        parts.push(format!(
            "a glossy target's highlight where each beam's reflection faces: {}",
            facing_seen.join(", ")
        ));
    }
    if !unjudged.is_empty() {
        let list: Vec<String> = unjudged.iter().map(|l| format!("mirror {l}")).collect();
        parts.push(format!(
            "{}: a reflection that faces no view, so the glossy target shows nothing there (a \
             diffuse one would)",
            list.join(", ")
        ));
    }
    if !alike.is_empty() {
        let mut lit = format!("the sample's views lit: {} of full scale", alike.join(", "));
        if facing.iter().any(Option::is_some) {
            lit += " (views alike: which mirror the beam lit is not told; a glossy black \
                    target on the holder tells)";
        }
        parts.push(lit);
    }
    let mut detail = parts.join("; ");
    if report.retakes > 0 {
        detail += &format!(" ({} steps taken again)", report.retakes);
    }
    if let Some(strobe) = report.strobe.describe(o.scan.light_margin_us) {
        detail += &format!("; {strobe}");
    }
    Ok(Ok(detail))
}

/// How many ADC codes the level `level` lies above `dark` (both in full
/// scale, the sensor's top code `max_code`).
fn codes_above(level: f64, dark: f64, max_code: f64) -> f64 {
    (level - dark) * max_code
}

fn saturation(share: f64) -> String {
    if share > 0.0 { format!(" ({:.1} % saturated)", 100.0 * share) } else { String::new() }
}

fn ms(d: Duration) -> f64 {
    d.as_secs_f64() * 1000.0
}

#[cfg(test)]
mod tests {
    use super::*;

    /// The default scanner's first and third rings face a view (their
    /// lights' reflections 1.5–1.6° from it), the others do not (≈ 11°):
    /// the check captures at the first, middle and last of those 16.
    #[test]
    fn the_capture_check_takes_mirrors_whose_reflection_faces_a_view() {
        let g = ScannerGeometry::default_scanner();
        let facing = facing_views(&g);
        let lights: Vec<usize> = (0..40).filter(|&l| facing[l].is_some()).collect();
        let want: Vec<usize> = (0..4).chain(13..25).collect();
        assert_eq!(lights, want);
        // Each faces the view across the holder: the same ring, half a turn on.
        assert_eq!(
            (facing[0], facing[2], facing[13], facing[19]),
            (Some(2), Some(0), Some(19), Some(13))
        );
        // And the outermost mirror, whatever the target shows there.
        assert_eq!(capture_mirrors(40, &facing, false), [0, 17, 24, 39]);
        let all: Vec<usize> = want.iter().copied().chain([39]).collect();
        assert_eq!(capture_mirrors(40, &facing, true), all);
        // A scanner none of whose lights faces a view: first, middle, last.
        assert_eq!(capture_mirrors(40, &[None; 40], false), [0, 20, 39]);
        assert_eq!(capture_mirrors(3, &[None; 3], true), [0, 1, 2]);
        assert_eq!(capture_mirrors(1, &[None], false), [0]);
        assert_eq!(capture_mirrors(0, &[], false), Vec::<usize>::new());
    }

    /// A highlight outshines the next view 4× and the median 8×; a diffuse
    /// sample's views, within a factor of two, show none.
    #[test]
    fn a_highlight_is_one_view_far_above_the_rest() {
        let views = |top: f64, next: f64, rest: f64| -> Vec<(usize, f64)> {
            (0..40)
                .map(|j| {
                    (
                        j,
                        if j == 7 {
                            top
                        } else if j == 8 {
                            next
                        } else {
                            rest
                        },
                    )
                })
                .collect()
        };
        assert_eq!(highlight(&views(3000.0, 2.0, 0.5)), Some(7));
        assert_eq!(highlight(&views(400.0, 100.0, 20.0)), Some(7));
        assert_eq!(highlight(&views(400.0, 101.0, 20.0)), None);
        assert_eq!(highlight(&views(400.0, 90.0, 51.0)), None);
        // A diffuse target: views alike.
        assert_eq!(highlight(&views(900.0, 800.0, 500.0)), None);
        // Too faint to count, however alone.
        assert_eq!(highlight(&views(15.0, 0.0, 0.0)), None);
    }

    /// Where the beam went, from the views' levels against the dark
    /// frame's: nowhere, unknown (views alike), the facing view, or a view
    /// another light faces.
    #[test]
    fn the_beam_is_placed_by_the_view_its_highlight_shows_in() {
        let top = 4095.0;
        let g = ScannerGeometry::default_scanner();
        let r = Reflections::of(&g);
        let dark = vec![Some(2.0 / top); 40];
        let lit = |bright: &[(usize, f64)], rest: f64| -> Vec<Option<f64>> {
            (0..40)
                .map(|j| {
                    let codes = bright.iter().find(|b| b.0 == j).map_or(rest, |b| b.1);
                    Some((2.0 + codes) / top)
                })
                .collect()
        };
        let beam = |views: &[Option<f64>], l| beam_of(l, views, &dark, &r, top, 0.5);
        // Nothing 16 codes above the dark frame: the beam missed.
        assert_eq!(beam(&lit(&[(2, 15.0)], 1.0), 0), None);
        // Every view alike: a diffuse sample.
        assert_eq!(beam(&lit(&[], 300.0), 0), Some(Beam::Alike(0.5)));
        // Mirror 0's highlight in view 2, which its reflection faces.
        assert_eq!(beam(&lit(&[(2, 4000.0)], 3.0), 0), Some(Beam::Facing(2)));
        // In view 1 instead: mirror 3's reflection faces it.
        assert_eq!(
            beam(&lit(&[(1, 4000.0)], 3.0), 0),
            Some(Beam::Elsewhere { view: 1, expected: Some(2), from: Some(3) })
        );
        // In a view no light faces (the second ring's).
        assert_eq!(
            beam(&lit(&[(5, 4000.0)], 3.0), 13),
            Some(Beam::Elsewhere { view: 5, expected: Some(19), from: None })
        );
        // A light of the second ring faces no view: its highlight's tail
        // belongs in the view nearest its reflection (view 9, 10.8° off).
        assert_eq!(r.nearest[4], Some(9));
        assert_eq!(beam(&lit(&[(9, 400.0)], 3.0), 4), Some(Beam::Facing(9)));
        assert_eq!(
            beam(&lit(&[(10, 400.0)], 3.0), 4),
            Some(Beam::Elsewhere { view: 10, expected: Some(9), from: None })
        );
        // A view outside the frame is left out, not taken as dark.
        let mut views = lit(&[(2, 4000.0)], 3.0);
        views[7] = None;
        assert_eq!(beam(&views, 0), Some(Beam::Facing(2)));
    }

    /// An unlit step names the causes; through a mirror whose reflection
    /// faces no view, also that a glossy target cannot show there.
    #[test]
    fn an_unlit_step_says_why_it_may_be() {
        let facing = [Some(2), None];
        let faced = unlit(0, &facing);
        assert!(faced.starts_with("mirror 0: no view of the sample 16 codes above"), "{faced}");
        assert!(faced.ends_with("or no sample is on the holder"), "{faced}");
        assert!(unlit(1, &facing).ends_with(
            "no sample is on the holder; a glossy target lit through this mirror shows its \
             highlight in no view: check with a diffuse one"
        ));
    }

    #[test]
    fn a_frame_counts_as_lit_only_well_above_the_dark_frame() {
        let top = 4095.0;
        // The dark frame's own level, or read noise above it: not lit.
        assert!(codes_above(3.0 / top, 3.0 / top, top) < LIT_CODES);
        assert!(codes_above(15.0 / top, 0.0, top) < LIT_CODES);
        // A black level carried by both frames does not count.
        assert!(codes_above(70.0 / top, 64.0 / top, top) < LIT_CODES);
        assert!(codes_above(81.0 / top, 64.0 / top, top) >= LIT_CODES);
        // A white target at half scale is far above.
        assert!(codes_above(0.5, 0.0, top) > 100.0 * LIT_CODES);
    }
}
