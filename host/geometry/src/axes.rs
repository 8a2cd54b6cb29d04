//! The axis configuration file (`docs/axis-config.md`): a device's three
//! [`AxisConfig`]s — steps per unit, travel, speeds and homing — as TOML, so
//! that a scanner built with other drives (another lead screw, belt ratio or
//! travel) can be configured from the host (`scanner axes --set`) and a
//! design checked against its travel (`scanner geometry --axes`).
//!
//! The fields are the wire's, in steps, so that a file read from a device
//! and written back is the same configuration bit for bit; the comments the
//! writer adds give them in the axis' units.

use std::path::{Path, PathBuf};

use protocol::{Axis, AxisConfig, AxisConfigProblem, Unit};
use serde::{Deserialize, Serialize};

use crate::unit_suffix;

/// Version of the axis configuration file format.
pub const AXES_FORMAT: u32 = 1;

/// The file's contents.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
struct AxesFile {
    format: u32,
    disk: AxisConfig,
    track: AxisConfig,
    tilt: AxisConfig,
}

/// Why an axis configuration file (or a set of configurations) was refused.
#[derive(Debug, thiserror::Error)]
pub enum AxesError {
    /// The file could not be read.
    #[error("cannot read {path}: {source}")]
    Io {
        /// The file.
        path: PathBuf,
        /// Why.
        source: std::io::Error,
    },
    /// A file that does not parse or validate.
    #[error("{path}: {source}")]
    File {
        /// The file.
        path: PathBuf,
        /// What is wrong with it.
        source: Box<AxesError>,
    },
    /// Not valid TOML, a missing key or a value of the wrong type.
    #[error("not an axis configuration: {0}")]
    Parse(#[from] toml::de::Error),
    /// A key the format does not have (a typo would otherwise be ignored).
    #[error("unknown key `{0}`")]
    UnknownKey(String),
    /// Another version of the format.
    #[error("format {0} (this build reads {AXES_FORMAT})")]
    Format(u32),
    /// A configuration no controller executes ([`AxisConfig::problem`]).
    #[error("{}: {problem}", axis.name())]
    Refused {
        /// The axis.
        axis: Axis,
        /// The controller's rule it breaks.
        problem: AxisConfigProblem,
    },
    /// A unit other than the one the kinematics give the axis' positions in.
    #[error(
        "{}: unit must be {:?}: the kinematics give its positions in {}",
        axis.name(),
        expected,
        match expected { Unit::Degree => "degrees", Unit::Millimetre => "millimetres" }
    )]
    Unit {
        /// The axis.
        axis: Axis,
        /// Its unit.
        expected: Unit,
    },
    /// The linear track cannot wrap.
    #[error("track: a linear axis cannot be continuous")]
    ContinuousTrack,
    /// A measured move that cannot correct an axis ([`Measured`]).
    #[error(
        "{}: commanded {}{u}, measured {}{u}: {why}",
        axis.name(),
        crate::shown(*commanded),
        crate::shown(*measured),
        u = match axis { Axis::Track => " mm", Axis::Disk | Axis::Tilt => "°" }
    )]
    Measurement {
        /// The axis.
        axis: Axis,
        /// The move the axis was told to make, in its unit.
        commanded: f64,
        /// The move measured on the machine, in its unit.
        measured: f64,
        /// What is wrong with them.
        why: String,
    },
    /// A continuous rotary axis whose revolution is not 360° of its steps.
    #[error(
        "{}: steps_per_rev = {steps_per_rev} is not one turn at {per_unit} steps/° \
         ({expected} steps)",
        axis.name()
    )]
    Revolution {
        /// The axis.
        axis: Axis,
        /// The file's steps per revolution.
        steps_per_rev: u32,
        /// Its steps per degree.
        per_unit: f32,
        /// 360 × `per_unit`, rounded.
        expected: i64,
    },
}

/// Whether the host can drive a scanner with these configurations (protocol
/// axis order): each one the controller accepts, in the units the
/// kinematics use (disk and tilt in degrees, track in millimetres), the
/// track limited, and a continuous axis' revolution 360° of its steps.
pub fn check_axes(axes: &[AxisConfig; 3]) -> Result<(), AxesError> {
    for (axis, c) in Axis::ALL.into_iter().zip(axes) {
        if let Some(problem) = c.problem() {
            return Err(AxesError::Refused { axis, problem });
        }
        let expected = match axis {
            Axis::Track => Unit::Millimetre,
            Axis::Disk | Axis::Tilt => Unit::Degree,
        };
        if c.unit != expected {
            return Err(AxesError::Unit { axis, expected });
        }
        if axis == Axis::Track && c.continuous {
            return Err(AxesError::ContinuousTrack);
        }
        let turn = (360.0 * c.steps_per_unit as f64).round() as i64;
        if c.continuous && turn != c.steps_per_rev as i64 {
            return Err(AxesError::Revolution {
                axis,
                steps_per_rev: c.steps_per_rev,
                per_unit: c.steps_per_unit,
                expected: turn,
            });
        }
    }
    Ok(())
}

/// What in `axes` (protocol axis order) a controller accepts but may not
/// be meant: a limited axis whose soft limits reach past its home switch on
/// the side homing approaches it from. With a flag sensor in mid-travel
/// that is right; with a limit switch at the end of the travel the axis
/// can be driven into its end stop. One line per axis.
pub fn axes_warnings(axes: &[AxisConfig; 3]) -> Vec<String> {
    Axis::ALL
        .into_iter()
        .zip(axes)
        .filter(|(_, c)| !c.continuous)
        .filter_map(|(axis, c)| {
            let home = c.homing.home_position;
            let (limit, beyond, side, direction) = match c.homing.direction {
                protocol::Direction::Negative => (c.min_steps, c.min_steps < home, "below", "down"),
                protocol::Direction::Positive => (c.max_steps, c.max_steps > home, "above", "up"),
            };
            beyond.then(|| {
                let per = c.steps_per_unit as f64;
                let u = unit_suffix(c.unit);
                format!(
                    "{}: the travel reaches {:.2}{u} ({limit} steps), {side} the home switch at \
                     {:.2}{u} ({home} steps) that homing meets going {direction}: right for a \
                     flag sensor within the travel, not for a limit switch at its end",
                    axis.name(),
                    limit as f64 / per,
                    home as f64 / per,
                )
            })
        })
        .collect()
}

/// A move an axis was told to make and the move measured on the machine
/// (`scanner axes --correct AXIS=COMMANDED:MEASURED`), in the axis' unit:
/// `track=100:98.7` — told to go 100 mm, it went 98.7 mm.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Measured {
    /// The axis.
    pub axis: Axis,
    /// The move it was told to make.
    pub commanded: f64,
    /// The move measured.
    pub measured: f64,
}

impl std::str::FromStr for Measured {
    type Err = String;

    fn from_str(s: &str) -> Result<Measured, String> {
        let wrong = || format!("`{s}`: expected AXIS=COMMANDED:MEASURED, e.g. track=100:98.7");
        let (name, moves) = s.split_once('=').ok_or_else(wrong)?;
        let (commanded, measured) = moves.split_once(':').ok_or_else(wrong)?;
        let axis = Axis::ALL
            .into_iter()
            .find(|a| a.name() == name.trim())
            .ok_or_else(|| format!("`{name}`: no such axis (disk, track, tilt)"))?;
        let number = |t: &str| t.trim().parse::<f64>().map_err(|_| wrong());
        Ok(Measured { axis, commanded: number(commanded)?, measured: number(measured)? })
    }
}

/// The largest factor [`correct_axis`] applies to an axis' steps per unit:
/// beyond 4× (or ¼) a measurement is not a calibration but a wrong
/// microstepping, gear or pitch, which is better read off the drive.
pub const MAX_CORRECTION: f64 = 4.0;

/// `config` corrected by a measured move: its steps per unit scaled by
/// commanded / measured (the steps it took moved the axis `measured`, so
/// that many steps make `measured`, not `commanded`). The positions keep
/// their units — soft limits, home position, back-off and homing search
/// are scaled with it, a continuous axis' revolution rounded to whole
/// steps and its steps per unit made 1/360 of it — while speeds and
/// accelerations keep their steps/s and steps/s², the rates the motor
/// was measured running at. The result is checked as a whole
/// ([`check_axes`] on the caller's side).
pub fn correct_axis(config: &AxisConfig, m: Measured) -> Result<AxisConfig, AxesError> {
    let refuse = |why: &str| AxesError::Measurement {
        axis: m.axis,
        commanded: m.commanded,
        measured: m.measured,
        why: why.to_string(),
    };
    if !(m.commanded.is_finite() && m.measured.is_finite())
        || m.commanded == 0.0
        || m.measured == 0.0
    {
        return Err(refuse("both must be finite and non-zero"));
    }
    let ratio = m.commanded / m.measured;
    if ratio < 0.0 {
        return Err(refuse("the axis moved the other way: swap one of its motor's coil pairs"));
    }
    if !(1.0 / MAX_CORRECTION..=MAX_CORRECTION).contains(&ratio) {
        return Err(refuse(&format!(
            "more than {MAX_CORRECTION}× off: check the driver's microstepping and the gear, \
             belt or screw"
        )));
    }
    let too_far = || refuse("the corrected travel does not fit in steps");
    let position = |steps: i32| -> Result<i32, AxesError> {
        let v = (steps as f64 * ratio).round();
        (v.abs() <= i32::MAX as f64).then_some(v as i32).ok_or_else(too_far)
    };
    let distance = |steps: u32| -> Result<u32, AxesError> {
        let v = (steps as f64 * ratio).round();
        (v <= u32::MAX as f64).then_some(v as u32).ok_or_else(too_far)
    };
    let mut c = *config;
    c.steps_per_unit = (config.steps_per_unit as f64 * ratio) as f32;
    if config.continuous && config.steps_per_rev > 0 {
        c.steps_per_rev = distance(config.steps_per_rev)?;
        c.steps_per_unit = (c.steps_per_rev as f64 / 360.0) as f32;
    }
    c.min_steps = position(config.min_steps)?;
    c.max_steps = if config.continuous && config.max_steps as i64 + 1 == config.steps_per_rev as i64
    {
        c.steps_per_rev as i32 - 1
    } else {
        position(config.max_steps)?
    };
    c.homing.home_position = position(config.homing.home_position)?;
    c.homing.backoff_steps = distance(config.homing.backoff_steps)?;
    c.homing.max_travel_steps = distance(config.homing.max_travel_steps)?;
    Ok(c)
}

/// The configurations of a file's text, checked ([`check_axes`]).
pub fn axes_from_toml(text: &str) -> Result<[AxisConfig; 3], AxesError> {
    let value: toml::Table = text.parse()?;
    let reference = toml::Table::try_from(file_of(&protocol::default_axes()))
        .expect("axis configurations serialise");
    if let Some(key) = unknown_key(&value, &reference, "") {
        return Err(AxesError::UnknownKey(key));
    }
    let file: AxesFile = toml::from_str(text)?;
    if file.format != AXES_FORMAT {
        return Err(AxesError::Format(file.format));
    }
    let axes = [file.disk, file.track, file.tilt];
    check_axes(&axes)?;
    Ok(axes)
}

/// The configurations of the file at `path`; errors name it.
pub fn load_axes(path: &Path) -> Result<[AxisConfig; 3], AxesError> {
    let text = scanner_formats::input::read_to_string(path)
        .map_err(|source| AxesError::Io { path: path.to_path_buf(), source })?;
    axes_from_toml(&text)
        .map_err(|e| AxesError::File { path: path.to_path_buf(), source: Box::new(e) })
}

/// The file text of `axes` (protocol axis order), each axis introduced by a
/// comment that gives it in its units ([`describe_axis`]).
pub fn axes_to_toml(axes: &[AxisConfig; 3]) -> String {
    let mut body = toml::to_string(&file_of(axes)).expect("axis configurations serialise");
    for (axis, c) in Axis::ALL.into_iter().zip(axes) {
        let header = format!("\n[{}]\n", axis.name());
        let comment = format!("\n# {}\n[{}]\n", describe_axis(c), axis.name());
        body = body.replacen(&header, &comment, 1);
    }
    format!(
        "# Axis configuration (format {AXES_FORMAT}); see docs/axis-config.md.\n\
         # Positions, distances and speeds in steps, steps/s and steps/s².\n\n{body}"
    )
}

/// One line on an axis in its units: resolution, travel, speed and
/// acceleration.
pub fn describe_axis(c: &AxisConfig) -> String {
    let per = c.steps_per_unit as f64;
    let u = unit_suffix(c.unit);
    let travel = if c.continuous {
        format!("continuous, {} steps/rev", c.steps_per_rev)
    } else {
        format!(
            "{:.2} … {:.2}{u} ({} … {} steps)",
            c.min_steps as f64 / per,
            c.max_steps as f64 / per,
            c.min_steps,
            c.max_steps
        )
    };
    let u = u.trim_start();
    format!(
        "{} steps/{u}, {travel}, v max {:.2} {u}/s, a max {:.2} {u}/s²",
        c.steps_per_unit,
        c.v_max as f64 / per,
        c.a_max as f64 / per,
    )
}

fn file_of(axes: &[AxisConfig; 3]) -> AxesFile {
    AxesFile { format: AXES_FORMAT, disk: axes[0], track: axes[1], tilt: axes[2] }
}

/// The first key of `value` (dotted from `prefix`) that `reference` does not
/// have at the same place.
fn unknown_key(value: &toml::Table, reference: &toml::Table, prefix: &str) -> Option<String> {
    value.iter().find_map(|(k, v)| {
        let key = if prefix.is_empty() { k.clone() } else { format!("{prefix}.{k}") };
        match (v, reference.get(k)) {
            (_, None) => Some(key),
            (toml::Value::Table(t), Some(toml::Value::Table(r))) => unknown_key(t, r, &key),
            _ => None,
        }
    })
}

#[cfg(test)]
mod tests {
    use super::*;

    fn defaults_text() -> String {
        axes_to_toml(&protocol::default_axes())
    }

    fn refused(text: &str) -> String {
        axes_from_toml(text).expect_err("refused").to_string()
    }

    #[test]
    fn the_defaults_round_trip_bit_for_bit() {
        let text = defaults_text();
        assert_eq!(axes_from_toml(&text).unwrap(), protocol::default_axes());
        assert!(
            text.contains(
                "\n# 1600 steps/mm, 0.00 … 200.00 mm (0 … 320000 steps), v max 40.00 mm/s"
            ),
            "{text}"
        );
        assert!(text.contains("\n# 44.444443 steps/°, continuous, 16000 steps/rev"), "{text}");
        assert!(
            text.contains("\n# 266.66666 steps/°, -35.00 … 35.00° (-9333 … 9333 steps)"),
            "{text}"
        );
    }

    #[test]
    fn a_changed_lead_screw_is_read() {
        let mut axes = protocol::default_axes();
        axes[1].steps_per_unit = 800.0;
        axes[1].max_steps = 120_000;
        assert_eq!(axes_from_toml(&axes_to_toml(&axes)).unwrap(), axes);
    }

    #[test]
    fn travel_beyond_the_home_switch_is_warned_of() {
        assert!(axes_warnings(&protocol::default_axes()).is_empty());
        let mut axes = protocol::default_axes();
        axes[1].min_steps = -1_600;
        axes[2].homing.direction = protocol::Direction::Positive;
        axes[2].homing.home_position = 0;
        let w = axes_warnings(&axes);
        assert_eq!(w.len(), 2, "{w:?}");
        assert!(w[0].starts_with(
            "track: the travel reaches -1.00 mm (-1600 steps), below the home switch at 0.00 mm \
             (0 steps) that homing meets going down"
        ), "{w:?}");
        assert!(w[1].starts_with("tilt: the travel reaches 35.00° (9333 steps), above"), "{w:?}");
    }

    #[test]
    fn unknown_keys_are_named() {
        let text = defaults_text();
        let typo = text.replacen("v_max = 5333", "v_maks = 5333", 1);
        assert_eq!(refused(&typo), "unknown key `tilt.v_maks`");
        let nested = text.replacen("timeout_ms = 40000", "timeout_ms = 40000\nretries = 2", 1);
        assert_eq!(refused(&nested), "unknown key `track.homing.retries`");
        assert_eq!(refused(&format!("extra = 1\n{text}")), "unknown key `extra`");
        let axis = format!("{text}\n[pan]\nunit = \"Degree\"\n");
        assert_eq!(refused(&axis), "unknown key `pan`");
    }

    #[test]
    fn what_a_controller_refuses_is_refused_with_its_rule() {
        let text = defaults_text();
        let nan = text.replacen("steps_per_unit = 1600.0", "steps_per_unit = nan", 1);
        assert_eq!(refused(&nan), "track: steps_per_unit must be a finite number above 0");
        let fast = text.replacen("v_max = 64000", "v_max = 200000", 1);
        assert_eq!(refused(&fast), "track: v_max must be 10 … 100000 steps/s");
        let limits = text.replacen("min_steps = -9333", "min_steps = 9333", 1);
        assert_eq!(refused(&limits), "tilt: min_steps must be below max_steps");
        let slow = text.replacen("slow_speed = 1600", "slow_speed = 20000", 1);
        assert!(
            refused(&slow).starts_with("track: homing.slow_speed must be"),
            "{}",
            refused(&slow)
        );
    }

    #[test]
    fn what_the_kinematics_cannot_use_is_refused() {
        let text = defaults_text();
        let unit = text.replacen("unit = \"Millimetre\"", "unit = \"Degree\"", 1);
        assert_eq!(
            refused(&unit),
            "track: unit must be Millimetre: the kinematics give its positions in millimetres"
        );
        let turn = text.replacen("steps_per_rev = 16000", "steps_per_rev = 16001", 1);
        assert_eq!(
            refused(&turn),
            "disk: steps_per_rev = 16001 is not one turn at 44.444443 steps/° (16000 steps)"
        );
        let mut axes = protocol::default_axes();
        axes[1].continuous = true;
        axes[1].steps_per_rev = 1000;
        assert_eq!(
            check_axes(&axes).unwrap_err().to_string(),
            "track: a linear axis cannot be continuous"
        );
    }

    #[test]
    fn bad_files_are_refused_with_their_name() {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("axes.toml");
        std::fs::write(&path, defaults_text().replacen("format = 1", "format = 2", 1)).unwrap();
        let e = load_axes(&path).unwrap_err().to_string();
        assert!(e.starts_with(&path.display().to_string()), "{e}");
        assert!(e.ends_with("format 2 (this build reads 1)"), "{e}");
        std::fs::write(&path, "format = 1\n[disk]\nunit = 3\n").unwrap();
        assert!(load_axes(&path).unwrap_err().to_string().contains("not an axis configuration"));
        std::fs::write(&path, defaults_text().replacen("min_steps = 0", "min_steps = -1.5", 1))
            .unwrap();
        assert!(load_axes(&path).unwrap_err().to_string().contains("not an axis configuration"));
        let missing = dir.path().join("missing.toml");
        assert!(load_axes(&missing).unwrap_err().to_string().starts_with("cannot read"));
    }

    fn measured(text: &str) -> Measured {
        text.parse().unwrap()
    }

    #[test]
    fn a_measured_move_corrects_the_steps_and_keeps_the_positions_units() {
        let [disk, track, tilt] = protocol::default_axes();
        // Told 100 mm, went 98.7 mm: 1600 steps made 0.987 mm.
        let m = measured("track=100:98.7");
        assert_eq!((m.axis, m.commanded, m.measured), (Axis::Track, 100.0, 98.7));
        let c = correct_axis(&track, m).unwrap();
        let ratio = 100.0 / 98.7;
        assert!((c.steps_per_unit as f64 - 1600.0 * ratio).abs() < 1e-3, "{c:?}");
        // The travel, home position, back-off and search keep their mm.
        let mm = |steps: i32, per: f32| steps as f64 / per as f64;
        assert!((mm(c.max_steps, c.steps_per_unit) - mm(track.max_steps, 1600.0)).abs() < 1e-3);
        assert_eq!(c.min_steps, (track.min_steps as f64 * ratio).round() as i32);
        let h = (c.homing, track.homing);
        assert_eq!(h.0.backoff_steps, (h.1.backoff_steps as f64 * ratio).round() as u32);
        assert_eq!(h.0.max_travel_steps, (h.1.max_travel_steps as f64 * ratio).round() as u32);
        // The motor's rates stay.
        assert_eq!((c.v_max, c.a_max), (track.v_max, track.a_max));
        assert_eq!((h.0.fast_speed, h.0.slow_speed), (h.1.fast_speed, h.1.slow_speed));
        assert_eq!(h.0.timeout_ms, h.1.timeout_ms);
        // Homed at −35°, the tilt's home position keeps its degrees.
        let t = correct_axis(&tilt, measured(" tilt = 10 : 10.5 ")).unwrap();
        assert_eq!(t.homing.home_position, (-9_333.0f64 * 10.0 / 10.5).round() as i32);
        assert_eq!(t.min_steps, t.homing.home_position);
        // The disk's revolution stays whole steps, its steps/° 1/360 of it.
        let d = correct_axis(&disk, measured("disk=360:355")).unwrap();
        assert_eq!(d.steps_per_rev, (16_000.0f64 * 360.0 / 355.0).round() as u32);
        assert_eq!((d.min_steps, d.max_steps), (0, d.steps_per_rev as i32 - 1));
        let axes = [d, c, t];
        check_axes(&axes).unwrap();
        // What a measurement cannot say.
        let refused = |m: &str, config: &AxisConfig| {
            correct_axis(config, measured(m)).unwrap_err().to_string()
        };
        assert_eq!(
            refused("track=100:-100", &track),
            "track: commanded 100 mm, measured -100 mm: the axis moved the other way: swap one \
             of its motor's coil pairs"
        );
        assert!(refused("tilt=10:0", &tilt).ends_with("both must be finite and non-zero"));
        assert!(refused("tilt=nan:10", &tilt).ends_with("both must be finite and non-zero"));
        assert!(refused("track=1e300:1", &track).starts_with("track: commanded 1e300 mm, m"));
        assert!(refused("track=1:1e-300", &track).contains("measured 1e-300 mm"));
        let far = crate::unit_to_steps(Axis::Track, -1e300, &track).unwrap_err();
        assert_eq!(far.to_string(), "track: -1e300 is not a position");
        assert!(refused("disk=360:80", &disk).contains("more than 4× off"));
        assert!(correct_axis(&disk, measured("disk=360:90")).is_ok(), "4× exactly");
        let mut long = track;
        long.max_steps = i32::MAX / 2;
        assert!(refused("track=4:1", &long).ends_with("does not fit in steps"));
        for bad in ["track", "track=100", "belt=1:2", "track=a:1", "track=1:2:3"] {
            assert!(bad.parse::<Measured>().is_err(), "{bad}");
        }
    }
}
