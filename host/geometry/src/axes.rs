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
}
