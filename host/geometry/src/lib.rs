//! # scanner-geometry
//!
//! The scanner's **nominal** geometry and its kinematics — the one file the
//! host gets (`docs/scanner-geometry.md` documents the format): the mirror
//! array, camera, sensor and source, forward and inverse kinematics, the
//! mirror table, unit ↔ step conversion of the axes (with the continuous
//! disk's wrap), the projection of the sample into the camera through each
//! mirror, and the geometry hash that names a scanner in scans and
//! calibrations.
//!
//! Frame: the sample centre is the first focus F1 at the origin, the sample
//! faces −z (down, towards the mirrors); the camera's pinhole is the second
//! focus F2 = (0, 0, d) on the axis above it. The mirrors are tangent to the
//! ellipsoid of revolution with foci F1, F2 and semi-major axis a, below the
//! sample. The source rides a radial track on a disk in the plane
//! z = `disk_height_mm` (above the camera, which looks through the disk's
//! aperture); a fold mirror on the carriage sends the beam down, tilted by
//! twice the fold mirror's tilt in the disk's radial plane.
//!
//! This crate is on the host's side of the line: the host computes the
//! device's mirror table and its first guess of every mirror's view from it.
//! The simulator (`hil-sim`) depends on it and renders with a seeded
//! *as-built* copy (its `AsBuilt::perturbed`) that the host never sees, so
//! the difference is what calibration has to recover.

pub mod axes;
pub mod check;
pub mod face;
pub mod polygon;

pub use axes::{
    AxesError, Measured, axes_from_toml, axes_to_toml, axes_warnings, check_axes, correct_axis,
    describe_axis, load_axes,
};
pub use check::{DesignCheck, DesignProblem, MirrorCheck};
pub use face::SampleFace;
pub use glam::DVec3;
use serde::{Deserialize, Serialize};
use sha2::{Digest, Sha256};

/// Version of the geometry file format.
pub const GEOMETRY_FORMAT: u32 = 1;

/// The default geometry file (spec/hardware.md, "Optics"), as shipped.
pub const DEFAULT_GEOMETRY_TOML: &str = include_str!("../config/default-geometry.toml");

/// Why a geometry file was refused.
#[derive(Debug, thiserror::Error)]
pub enum GeometryError {
    /// The file could not be read.
    #[error("cannot read {path}: {source}")]
    Io {
        /// The file.
        path: std::path::PathBuf,
        /// Why.
        source: std::io::Error,
    },
    /// Not valid TOML or not the schema.
    #[error("scanner geometry: {0}")]
    Parse(#[from] toml::de::Error),
    /// A value out of its physical range (the message names the field).
    #[error("scanner geometry: {0}")]
    Invalid(String),
    /// A geometry file that does not parse or validate.
    #[error("{path}: {source}")]
    File {
        /// The file.
        path: std::path::PathBuf,
        /// What is wrong with it ([`GeometryError::Parse`] or
        /// [`GeometryError::Invalid`] and the others of validation).
        source: Box<GeometryError>,
    },
    /// The mirror index does not exist.
    #[error("no mirror {0} (the geometry has {1})")]
    NoMirror(usize, usize),
    /// The mirror's axis positions are outside the device's travel.
    #[error("mirror {0} is out of the device's range: {1}")]
    OutOfTravel(usize, StepsError),
    /// Kinematics cannot aim at the mirror.
    #[error("mirror {0} cannot be reached: {1}")]
    Unreachable(usize, String),
}

/// The ellipsoid the mirrors are tangent to.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct Ellipsoid {
    /// Semi-major axis a, mm.
    pub semi_major_mm: f64,
    /// Distance between the foci d (sample to camera), mm.
    pub focal_distance_mm: f64,
}

impl Ellipsoid {
    /// The second focus (camera pinhole).
    pub fn f2(&self) -> DVec3 {
        DVec3::new(0.0, 0.0, self.focal_distance_mm)
    }

    /// The point of the ellipsoid in unit direction `w` from F1:
    /// r(ω) = (4a² − d²) / (4a − 2d ω_z).
    pub fn point_towards(&self, w: DVec3) -> DVec3 {
        let (a, d) = (self.semi_major_mm, self.focal_distance_mm);
        w * ((4.0 * a * a - d * d) / (4.0 * a - 2.0 * d * w.z))
    }

    /// Unit normal of the tangent plane at `p`, pointing inside (towards the foci).
    pub fn inward_normal(&self, p: DVec3) -> DVec3 {
        -((p).normalize() + (p - self.f2()).normalize()).normalize()
    }
}

/// The sample and its holder.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct SampleMount {
    /// Side of the square sample, mm.
    pub size_mm: f64,
    /// Radius of the holder around it (opaque, black), mm.
    pub holder_radius_mm: f64,
}

/// Pinhole camera, with radial lens distortion if its lens has some.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct CameraSpec {
    /// Pinhole position, mm.
    pub position_mm: [f64; 3],
    /// Optical axis (unit).
    pub forward: [f64; 3],
    /// Image "up" (unit, ⟂ forward); image rows run against it.
    pub up: [f64; 3],
    /// Sensor width, px.
    pub width: u32,
    /// Sensor height, px.
    pub height: u32,
    /// Focal length, px.
    pub focal_px: f64,
    /// Principal point (x, y), px from the top-left corner.
    pub principal_px: [f64; 2],
    /// Radial lens distortion (k1, k2) ([`radial_distort`]); absent: none.
    #[serde(default, skip_serializing_if = "is_pinhole")]
    pub distortion: [f64; 2],
}

fn is_pinhole(k: &[f64; 2]) -> bool {
    *k == [0.0; 2]
}

/// Radial lens distortion of normalised image coordinates n = (X/Z, Y/Z)
/// (camera frame: x right, y down, z forward): n · (1 + k1 r² + k2 r⁴),
/// r² = |n|² — the Brown–Conrady radial terms (OpenCV's k1, k2). k1 < 0
/// is barrel distortion, k1 > 0 pincushion.
pub fn radial_distort(k: [f64; 2], n: [f64; 2]) -> [f64; 2] {
    let r2 = n[0] * n[0] + n[1] * n[1];
    let s = 1.0 + r2 * (k[0] + k[1] * r2);
    [n[0] * s, n[1] * s]
}

/// The inverse of [`radial_distort`] (Newton's method on the radius), for
/// distortions that are monotonic over the image ([`ScannerGeometry::validate`]).
pub fn radial_undistort(k: [f64; 2], d: [f64; 2]) -> [f64; 2] {
    if k == [0.0; 2] {
        return d;
    }
    let rd = d[0].hypot(d[1]);
    if rd == 0.0 {
        return d;
    }
    let mut r = rd;
    for _ in 0..30 {
        let r2 = r * r;
        let f = r * (1.0 + r2 * (k[0] + k[1] * r2)) - rd;
        let step = f / radial_slope(k, r);
        r -= step;
        if step.abs() < 1e-15 {
            break;
        }
    }
    [d[0] * r / rd, d[1] * r / rd]
}

/// How fast [`radial_distort`]'s radius grows with the undistorted one at
/// radius `r`: d r_d / d r = 1 + 3 k1 r² + 5 k2 r⁴ (one to one while > 0).
pub fn radial_slope(k: [f64; 2], r: f64) -> f64 {
    let r2 = r * r;
    1.0 + r2 * (3.0 * k[0] + 5.0 * k[1] * r2)
}

/// Whether [`radial_distort`] with `k` maps radii 0…`r_max` one to one:
/// k finite, and [`radial_slope`] clear of 0 (> 0.05) at 101 radii over
/// that span.
pub fn radial_one_to_one(k: [f64; 2], r_max: f64) -> bool {
    k.iter().all(|v| v.is_finite())
        && (0..=100).all(|i| radial_slope(k, r_max * i as f64 / 100.0) > 0.05)
}

impl CameraSpec {
    /// (right, down, forward) unit vectors of the image.
    pub fn basis(&self) -> (DVec3, DVec3, DVec3) {
        let f = DVec3::from(self.forward).normalize();
        let up = DVec3::from(self.up);
        let right = f.cross(up).normalize();
        let down = f.cross(right).normalize();
        (right, down, f)
    }

    /// Unit direction of the ray through image point (x, y) (pixel centres
    /// are at half-integers).
    pub fn ray(&self, x: f64, y: f64) -> DVec3 {
        let (r, dn, f) = self.basis();
        let n = self.undistorted(x, y);
        (f + r * n[0] + dn * n[1]).normalize()
    }

    /// Normalised image coordinates (X/Z, Y/Z) of the ray through image
    /// point (x, y): the lens' distortion undone.
    pub fn undistorted(&self, x: f64, y: f64) -> [f64; 2] {
        let d = [
            (x - self.principal_px[0]) / self.focal_px,
            (y - self.principal_px[1]) / self.focal_px,
        ];
        radial_undistort(self.distortion, d)
    }

    /// Image point of world point `p` (None if behind the camera).
    pub fn project(&self, p: DVec3) -> Option<[f64; 2]> {
        let (r, dn, f) = self.basis();
        let v = p - DVec3::from(self.position_mm);
        let z = v.dot(f);
        (z > 1e-9).then(|| {
            let n = radial_distort(self.distortion, [v.dot(r) / z, v.dot(dn) / z]);
            [
                self.principal_px[0] + self.focal_px * n[0],
                self.principal_px[1] + self.focal_px * n[1],
            ]
        })
    }
}

/// Image sensor.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct SensorSpec {
    /// ADC resolution, bits.
    pub bits: u32,
    /// Full-well capacity, electrons (maps to the top ADC code).
    pub full_well_e: f64,
    /// Read noise, electrons RMS.
    pub read_noise_e: f64,
    /// Electrons per second per unit of scene radiance at the image centre.
    pub sensitivity_e: f64,
    /// Vignetting: relative illumination cos^k of the off-axis angle.
    pub vignetting_exponent: f64,
}

impl SensorSpec {
    /// Largest ADC code.
    pub fn max_code(&self) -> f64 {
        ((1u64 << self.bits) - 1) as f64
    }

    /// The integer that stands for the top code in an image of
    /// `file_bits`-bit integers whose capture program stores this sensor's
    /// codes as `codes` says (docs/scan-format.md, "Frames from a folder"):
    /// a value v of such an image is v / this, in the frames' unit.
    /// `None` when the file's integers are too narrow for the codes.
    pub fn integer_full_scale(&self, codes: IntegerCodes, file_bits: u32) -> Option<u64> {
        if file_bits < self.bits || file_bits > 32 {
            return None;
        }
        let top = (1u64 << self.bits) - 1;
        Some(match codes {
            IntegerCodes::Native => top,
            IntegerCodes::Shifted => top << (file_bits - self.bits),
            IntegerCodes::Scaled => (1u64 << file_bits) - 1,
        })
    }
}

/// How a camera's capture program stores the sensor's ADC codes in an image
/// of integers (a 16-bit PNG or TIFF, say, from a 12-bit sensor).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default, Serialize, Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum IntegerCodes {
    /// The codes themselves: 0 … 4 095 for 12 bits.
    #[default]
    Native,
    /// Shifted left to the integer's top bits: code × 16 (0 … 65 520) for
    /// 12 bits in 16; the low bits are 0.
    Shifted,
    /// Stretched over the integer's range: code × 65 535 / 4 095, rounded.
    Scaled,
}

impl IntegerCodes {
    /// The name on the command line and in files.
    pub fn name(self) -> &'static str {
        match self {
            IntegerCodes::Native => "native",
            IntegerCodes::Shifted => "shifted",
            IntegerCodes::Scaled => "scaled",
        }
    }
}

/// Source kinematics: disk, radial track, fold mirror, beam.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct SourceSpec {
    /// Height of the fold mirror's pivot (the disk plane), mm.
    pub disk_height_mm: f64,
    /// Track position the inverse kinematics uses for every mirror, mm.
    pub working_track_mm: f64,
    /// Disk angle at the index flag (axis position 0), degrees.
    pub disk_zero_deg: f64,
    /// Radius of the fold mirror's pivot at track position 0, mm.
    pub track_zero_mm: f64,
    /// Fold-mirror tilt at tilt position 0 (0 = beam straight down), degrees.
    pub tilt_zero_deg: f64,
    /// Beam radius at which the irradiance has fallen to zero, mm.
    pub beam_radius_mm: f64,
    /// Width of the beam's soft edge, mm (full irradiance inside
    /// `beam_radius_mm − beam_edge_mm`).
    pub beam_edge_mm: f64,
    /// Irradiance across the beam at full light duty (relative units).
    pub irradiance: f64,
}

impl SourceSpec {
    /// Relative irradiance at distance `r` from the beam axis.
    pub fn profile(&self, r: f64) -> f64 {
        let inner = self.beam_radius_mm - self.beam_edge_mm;
        if r <= inner {
            1.0
        } else if r >= self.beam_radius_mm {
            0.0
        } else {
            0.5 * (1.0 + (std::f64::consts::PI * (r - inner) / self.beam_edge_mm).cos())
        }
    }
}

/// One planar mirror: a square centred on `center_mm` with normal `normal`,
/// edges along the azimuthal direction and its perpendicular.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct MirrorSpec {
    /// Centre of the reflecting face, mm.
    pub center_mm: [f64; 3],
    /// Unit normal of the reflecting face (pointing at the foci).
    pub normal: [f64; 3],
    /// Side of the square, mm.
    pub size_mm: f64,
    /// Reflectance (all channels).
    pub reflectance: f64,
}

impl MirrorSpec {
    /// Centre.
    pub fn center(&self) -> DVec3 {
        DVec3::from(self.center_mm)
    }

    /// (normal, edge u, edge v) unit vectors.
    pub fn frame(&self) -> (DVec3, DVec3, DVec3) {
        let n = DVec3::from(self.normal).normalize();
        let t = DVec3::Z.cross(n);
        let t = if t.length() < 1e-9 { DVec3::X } else { t.normalize() };
        (n, t, n.cross(t))
    }

    /// Where the ray (origin, unit dir) meets the reflecting face inside the
    /// square: (distance, point). Hits from behind do not count.
    pub fn intersect(&self, origin: DVec3, dir: DVec3) -> Option<(f64, DVec3)> {
        self.facet().intersect(origin, dir)
    }

    /// The square with its frame computed once, for tracing many rays.
    pub fn facet(&self) -> Facet {
        let (n, u, v) = self.frame();
        Facet { center: self.center(), n, u, v, half: self.size_mm / 2.0 }
    }

    /// Mirror image of point `p` in the mirror's plane.
    pub fn reflect_point(&self, p: DVec3) -> DVec3 {
        reflect_in_plane(p, self.center(), DVec3::from(self.normal).normalize())
    }

    /// Mirror image of direction `d`.
    pub fn reflect_dir(&self, d: DVec3) -> DVec3 {
        let n = DVec3::from(self.normal).normalize();
        d - 2.0 * d.dot(n) * n
    }

    /// The square's corners.
    pub fn corners(&self) -> [DVec3; 4] {
        let (_, u, v) = self.frame();
        let h = self.size_mm / 2.0;
        let c = self.center();
        [c + (u + v) * h, c + (u - v) * h, c - (u + v) * h, c - (u - v) * h]
    }
}

/// A mirror square ready for ray intersection.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Facet {
    /// Centre.
    pub center: DVec3,
    /// Unit normal.
    pub n: DVec3,
    /// Unit edge directions.
    pub u: DVec3,
    /// Second edge direction.
    pub v: DVec3,
    /// Half the side.
    pub half: f64,
}

impl Facet {
    /// Where the ray (origin, unit dir) meets the front face inside the
    /// square: (distance, point).
    #[inline]
    pub fn intersect(&self, origin: DVec3, dir: DVec3) -> Option<(f64, DVec3)> {
        let denom = dir.dot(self.n);
        if denom >= -1e-12 {
            return None;
        }
        let t = (self.center - origin).dot(self.n) / denom;
        if t <= 1e-9 {
            return None;
        }
        let p = origin + dir * t;
        let q = p - self.center;
        (q.dot(self.u).abs() <= self.half && q.dot(self.v).abs() <= self.half).then_some((t, p))
    }

    /// Mirror image of direction `d`.
    #[inline]
    pub fn reflect_dir(&self, d: DVec3) -> DVec3 {
        d - 2.0 * d.dot(self.n) * self.n
    }
}

/// Positions of the three axes in their units (degrees, mm, degrees), as
/// measured from their home/index positions.
#[derive(Debug, Clone, Copy, PartialEq, Default, Serialize, Deserialize)]
pub struct AxisValues {
    /// Disk angle, degrees.
    pub disk_deg: f64,
    /// Track position, mm.
    pub track_mm: f64,
    /// Fold-mirror tilt, degrees.
    pub tilt_deg: f64,
}

impl AxisValues {
    /// As an array in protocol axis order.
    pub fn to_array(self) -> [f64; 3] {
        [self.disk_deg, self.track_mm, self.tilt_deg]
    }

    /// From an array in protocol axis order.
    pub fn from_array(a: [f64; 3]) -> AxisValues {
        AxisValues { disk_deg: a[0], track_mm: a[1], tilt_deg: a[2] }
    }

    /// Axis positions in steps under the device's axis configurations
    /// (protocol axis order), rounded to the nearest step; a continuous axis
    /// wraps into its revolution (−90° and 270° are the same step). Errors
    /// name the axis out of its range.
    pub fn to_steps(self, configs: &[protocol::AxisConfig; 3]) -> Result<[i32; 3], StepsError> {
        let values = self.to_array();
        let mut out = [0i32; 3];
        for (i, c) in configs.iter().enumerate() {
            out[i] = unit_to_steps(protocol::Axis::ALL[i], values[i], c)?;
        }
        Ok(out)
    }

    /// Axis values of positions in steps (protocol axis order); a
    /// continuous axis is taken modulo its revolution (one turn further is
    /// the same place).
    pub fn from_steps(steps: [i64; 3], configs: &[protocol::AxisConfig; 3]) -> AxisValues {
        AxisValues::from_array(std::array::from_fn(|i| steps_to_unit(steps[i], &configs[i])))
    }
}

/// Why an axis value has no step position.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
pub enum StepsError {
    /// Not a finite number of a sane size.
    #[error("{}: {} is not a position", axis.name(), shown(*value))]
    NotAPosition {
        /// The axis.
        axis: protocol::Axis,
        /// The value, in the axis' unit.
        value: f64,
    },
    /// Outside the axis' travel.
    #[error(
        "{}: {value:.3}{u} ({steps} steps) is outside its travel {:.2} … {:.2}{u} \
         ({min} … {max} steps)",
        axis.name(),
        *min as f64 / per_unit,
        *max as f64 / per_unit,
        u = unit_suffix(*unit)
    )]
    OutOfRange {
        /// The axis.
        axis: protocol::Axis,
        /// The value, in the axis' unit.
        value: f64,
        /// Steps, after a continuous axis' wrap.
        steps: i64,
        /// Travel limits, steps.
        min: i32,
        /// Travel limits, steps.
        max: i32,
        /// The axis' unit.
        unit: protocol::Unit,
        /// Its steps per unit.
        per_unit: f64,
    },
}

/// A number as a message shows it: as Rust writes it, but in scientific
/// notation beyond ±10⁹ and below 10⁻⁶ (not three hundred digits of 1e300).
pub fn shown(v: f64) -> String {
    if v != 0.0 && v.is_finite() && !(1e-6..1e9).contains(&v.abs()) {
        format!("{v:e}")
    } else {
        v.to_string()
    }
}

/// How a value of `unit` is written after its number: "°", " mm".
pub fn unit_suffix(unit: protocol::Unit) -> &'static str {
    match unit {
        protocol::Unit::Degree => "°",
        protocol::Unit::Millimetre => " mm",
    }
}

/// The one unit → step conversion: `value` (degrees or mm from home) of
/// `axis` in steps under `config`, rounded to the nearest step; a
/// continuous axis wraps into its revolution.
pub fn unit_to_steps(
    axis: protocol::Axis,
    value: f64,
    config: &protocol::AxisConfig,
) -> Result<i32, StepsError> {
    let steps = offset_to_steps(axis, value, config)? as i64;
    if config.continuous && config.steps_per_rev > 0 {
        // No soft limits: every angle is within its revolution, as the
        // device's own check says.
        return Ok(steps.rem_euclid(config.steps_per_rev as i64) as i32);
    }
    if steps < config.min_steps as i64 || steps > config.max_steps as i64 {
        return Err(StepsError::OutOfRange {
            axis,
            value,
            steps,
            min: config.min_steps,
            max: config.max_steps,
            unit: config.unit,
            per_unit: config.steps_per_unit as f64,
        });
    }
    Ok(steps as i32)
}

/// A relative move of `value` units in steps (no wrap, no travel check:
/// the device checks where it ends), rounded to the nearest step.
pub fn offset_to_steps(
    axis: protocol::Axis,
    value: f64,
    config: &protocol::AxisConfig,
) -> Result<i32, StepsError> {
    let raw = (value * config.steps_per_unit as f64).round();
    if !raw.is_finite() || raw.abs() > i32::MAX as f64 / 2.0 {
        return Err(StepsError::NotAPosition { axis, value });
    }
    Ok(raw as i32)
}

/// The one step → unit conversion (a continuous axis modulo its revolution).
pub fn steps_to_unit(steps: i64, config: &protocol::AxisConfig) -> f64 {
    let s = if config.continuous && config.steps_per_rev > 0 {
        steps.rem_euclid(config.steps_per_rev as i64)
    } else {
        steps
    };
    s as f64 / config.steps_per_unit as f64
}

/// A collimated beam: its axis leaves `origin` (on the fold mirror) along
/// `dir`.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Beam {
    /// A point of the beam axis.
    pub origin: DVec3,
    /// Unit direction of travel.
    pub dir: DVec3,
}

impl Beam {
    /// Distance of `p` from the beam axis.
    pub fn distance(&self, p: DVec3) -> f64 {
        let q = p - self.origin;
        (q - self.dir * q.dot(self.dir)).length()
    }
}

/// The scanner's geometry.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct ScannerGeometry {
    /// File format version ([`GEOMETRY_FORMAT`]).
    pub format: u32,
    /// The ellipsoid.
    pub ellipsoid: Ellipsoid,
    /// The sample.
    pub sample: SampleMount,
    /// The camera.
    pub camera: CameraSpec,
    /// Its sensor.
    pub sensor: SensorSpec,
    /// The source kinematics.
    pub source: SourceSpec,
    /// The mirrors, numbered from 0 in this order.
    #[serde(rename = "mirror")]
    pub mirrors: Vec<MirrorSpec>,
}

/// Mirror image of point `p` in the plane through `point` with unit
/// normal `normal` (a mirror's virtual image of the camera, say).
pub fn reflect_in_plane(p: DVec3, point: DVec3, normal: DVec3) -> DVec3 {
    p - 2.0 * (p - point).dot(normal) * normal
}

/// World ↔ sample-local frame: tangent +x, bitangent −y, normal −z (the
/// sample faces down). The map is its own inverse.
pub fn world_to_sample(v: DVec3) -> DVec3 {
    DVec3::new(v.x, -v.y, -v.z)
}

/// Sample-local ↔ world (same map as [`world_to_sample`]).
pub fn sample_to_world(v: DVec3) -> DVec3 {
    world_to_sample(v)
}

/// The largest magnitude of any number in a geometry file: a scanner of
/// up to a kilometre, in mm, with room for its squares in double precision.
pub const MAX_MAGNITUDE: f64 = 1e9;

/// Checks that every number of `value` (a scanner's geometry, or a
/// calibration of it) is finite and within ±[`MAX_MAGNITUDE`], or names the
/// first that is not by its key: `mirror[3].center_mm[1] = inf: not a
/// finite number within ±1e9`.
pub fn check_numbers(value: &impl Serialize) -> Result<(), String> {
    let value = toml::Value::try_from(value).map_err(|e| format!("not serialisable: {e}"))?;
    match first_unusable_number(&value, String::new()) {
        Some((key, x)) => {
            Err(format!("{key} = {x:e}: not a finite number within ±{MAX_MAGNITUDE:e}"))
        }
        None => Ok(()),
    }
}

/// The first number under `v` (a TOML value, `key` its dotted path) that is
/// not finite or exceeds [`MAX_MAGNITUDE`], with its key.
fn first_unusable_number(v: &toml::Value, key: String) -> Option<(String, f64)> {
    let child = |k: &dyn std::fmt::Display| {
        if key.is_empty() { k.to_string() } else { format!("{key}.{k}") }
    };
    match v {
        toml::Value::Float(x) if !x.is_finite() || x.abs() > MAX_MAGNITUDE => Some((key, *x)),
        toml::Value::Integer(i) if i.unsigned_abs() as f64 > MAX_MAGNITUDE => {
            Some((key, *i as f64))
        }
        toml::Value::Table(t) => t.iter().find_map(|(k, x)| first_unusable_number(x, child(k))),
        toml::Value::Array(a) => {
            a.iter().enumerate().find_map(|(i, x)| first_unusable_number(x, format!("{key}[{i}]")))
        }
        _ => None,
    }
}

/// Rings of the default layout: (polar angle from the sample normal, mirrors).
pub const DEFAULT_RINGS: [(f64, usize); 4] =
    [(15.0, 4), (31.666_666_666_666_664, 9), (48.333_333_333_333_336, 12), (65.0, 15)];

impl ScannerGeometry {
    /// The default scanner of spec/hardware.md, computed (the shipped file
    /// [`DEFAULT_GEOMETRY_TOML`] is this, written out).
    pub fn generate_default() -> ScannerGeometry {
        Self::generate_with_rings(&DEFAULT_RINGS)
    }

    /// The default scanner with its mirrors on other rings: (polar angle
    /// from the sample normal in degrees, mirrors), the odd rings
    /// staggered by half a mirror, as the default's are.
    pub fn generate_with_rings(rings: &[(f64, usize)]) -> ScannerGeometry {
        let ellipsoid = Ellipsoid { semi_major_mm: 600.0, focal_distance_mm: 800.0 };
        let mirrors = ring_mirrors(&ellipsoid, rings, 50.0, 0.92);
        ScannerGeometry {
            format: GEOMETRY_FORMAT,
            camera: CameraSpec {
                position_mm: ellipsoid.f2().to_array(),
                forward: [0.0, 0.0, -1.0],
                up: [0.0, 1.0, 0.0],
                width: 4096,
                height: 4096,
                focal_px: 5600.0,
                principal_px: [2048.0, 2048.0],
                distortion: [0.0; 2],
            },
            ellipsoid,
            sample: SampleMount { size_mm: 25.4, holder_radius_mm: 20.0 },
            sensor: SensorSpec {
                bits: 12,
                full_well_e: 10_000.0,
                read_noise_e: 3.0,
                sensitivity_e: 160_000.0,
                vignetting_exponent: 4.0,
            },
            source: SourceSpec {
                disk_height_mm: 830.0,
                working_track_mm: 30.0,
                disk_zero_deg: 0.0,
                track_zero_mm: 0.0,
                tilt_zero_deg: 0.0,
                beam_radius_mm: 24.0,
                beam_edge_mm: 4.0,
                irradiance: 1.0,
            },
            mirrors,
        }
    }

    /// This scanner with its mirrors replaced by rings of mirrors tangent
    /// to its ellipsoid, as [`Self::generate_with_rings`] places them: the
    /// camera, sensor, sample and source kept; each mirror of the size and
    /// reflectance of this scanner's first (50 mm, 0.92 if it has none).
    pub fn with_rings(&self, rings: &[(f64, usize)]) -> ScannerGeometry {
        let (size, reflectance) =
            self.mirrors.first().map_or((50.0, 0.92), |m| (m.size_mm, m.reflectance));
        ScannerGeometry {
            mirrors: ring_mirrors(&self.ellipsoid, rings, size, reflectance),
            ..self.clone()
        }
    }

    /// The shipped default geometry.
    pub fn default_scanner() -> ScannerGeometry {
        // The shipped file is checked against `generate_default` by a test.
        Self::from_toml(DEFAULT_GEOMETRY_TOML).expect("the shipped default geometry is valid")
    }

    /// Parse and validate a geometry file.
    pub fn from_toml(text: &str) -> Result<ScannerGeometry, GeometryError> {
        let g: ScannerGeometry = toml::from_str(text)?;
        g.validate()?;
        Ok(g)
    }

    /// Read a geometry file.
    pub fn load(path: &std::path::Path) -> Result<ScannerGeometry, GeometryError> {
        let text = scanner_formats::input::read_to_string(path)
            .map_err(|source| GeometryError::Io { path: path.to_path_buf(), source })?;
        Self::from_toml(&text)
            .map_err(|e| GeometryError::File { path: path.to_path_buf(), source: Box::new(e) })
    }

    /// The file text.
    pub fn to_toml(&self) -> String {
        let body = toml::to_string(self).expect("geometry serialises");
        format!(
            "# Scanner geometry (format {GEOMETRY_FORMAT}); see docs/scanner-geometry.md.\n\
             # Lengths in mm, angles in degrees, sample at the origin facing -z.\n\n{body}"
        )
    }

    /// SHA-256 of the canonical file text, hex: names this geometry in scans.
    pub fn hash(&self) -> String {
        let digest = Sha256::digest(toml::to_string(self).expect("geometry serialises"));
        digest.iter().map(|b| format!("{b:02x}")).collect()
    }

    /// Check what [`ScannerGeometry::from_toml`] checks of a file's contents.
    pub fn validate(&self) -> Result<(), GeometryError> {
        let bad = |m: String| Err(GeometryError::Invalid(m));
        if self.format != GEOMETRY_FORMAT {
            return bad(format!("format {} (this build reads {GEOMETRY_FORMAT})", self.format));
        }
        // TOML writes `nan` and `inf`; no key of the file means either, and
        // beyond ±MAX_MAGNITUDE a product of two lengths is no longer finite
        // in the kinematics and projections.
        check_numbers(self).map_err(GeometryError::Invalid)?;
        let e = &self.ellipsoid;
        if !(e.focal_distance_mm > 0.0 && e.semi_major_mm * 2.0 > e.focal_distance_mm) {
            return bad("ellipsoid needs 0 < focal_distance < 2 × semi_major".into());
        }
        if !(self.sample.size_mm > 0.0 && self.sample.holder_radius_mm >= 0.0) {
            return bad("sample size must be positive".into());
        }
        let c = &self.camera;
        if c.width == 0 || c.height == 0 || c.width > 16_384 || c.height > 16_384 {
            return bad(format!("camera {}×{} px outside 1…16384", c.width, c.height));
        }
        if !(c.focal_px.is_finite() && c.focal_px > 0.0) {
            return bad("camera focal_px must be positive".into());
        }
        // The distortion must map the image one to one: its radius grows
        // with the undistorted one out to beyond the sensor's corners.
        let corner = [0.0, c.width as f64]
            .iter()
            .flat_map(|&x| [0.0, c.height as f64].map(|y| (x, y)))
            .map(|(x, y)| (x - c.principal_px[0]).hypot(y - c.principal_px[1]) / c.focal_px)
            .fold(0.0, f64::max);
        let [k1, k2] = c.distortion;
        if !radial_one_to_one(c.distortion, 1.5 * corner) {
            return bad(format!(
                "camera distortion [{k1}, {k2}] does not map the image one to one"
            ));
        }
        let f = DVec3::from(c.forward);
        let up = DVec3::from(c.up);
        if !(f.length() > 0.5 && up.length() > 0.5 && f.normalize().cross(up).length() > 0.1) {
            return bad("camera forward and up must be unit-ish and not parallel".into());
        }
        let s = &self.sensor;
        let sensor_ok = (1..=16).contains(&s.bits)
            && s.full_well_e > 0.0
            && s.read_noise_e >= 0.0
            && s.sensitivity_e > 0.0
            && s.vignetting_exponent.is_finite();
        if !sensor_ok {
            return bad("sensor: bits 1…16, positive full well and sensitivity".into());
        }
        let src = &self.source;
        if !(src.beam_radius_mm > 0.0
            && src.beam_edge_mm > 0.0
            && src.beam_edge_mm <= src.beam_radius_mm
            && src.irradiance > 0.0)
        {
            return bad("source: 0 < beam_edge ≤ beam_radius, positive irradiance".into());
        }
        if self.mirrors.is_empty() || self.mirrors.len() > protocol::MAX_MIRRORS {
            return bad(format!("{} mirrors (1…{})", self.mirrors.len(), protocol::MAX_MIRRORS));
        }
        for (l, m) in self.mirrors.iter().enumerate() {
            let n = DVec3::from(m.normal);
            if !(n.is_finite() && (n.length() - 1.0).abs() < 1e-3) {
                return bad(format!("mirror {l}: normal must be a unit vector"));
            }
            if !(m.size_mm > 0.0 && (0.0..=1.0).contains(&m.reflectance)) {
                return bad(format!("mirror {l}: size > 0, reflectance in [0, 1]"));
            }
            let c = DVec3::from(m.center_mm);
            if !c.is_finite() {
                return bad(format!("mirror {l}: centre must be finite"));
            }
            // It must face the sample (which looks down −z) from beyond the
            // sample itself: its direction from the sample is then defined.
            if !(c.z < 0.0 && c.length() >= self.sample.size_mm) {
                return bad(format!(
                    "mirror {l}: centre {:?} mm must lie below the sample (z < 0), at least the \
                     sample's size ({} mm) from its centre",
                    m.center_mm, self.sample.size_mm
                ));
            }
        }
        Ok(())
    }

    /// Forward kinematics: the beam for axis positions `axes`.
    pub fn beam(&self, axes: AxisValues) -> Beam {
        let s = &self.source;
        let phi = (axes.disk_deg + s.disk_zero_deg).to_radians();
        let rho = axes.track_mm + s.track_zero_mm;
        let beta = 2.0 * (axes.tilt_deg + s.tilt_zero_deg).to_radians();
        let radial = DVec3::new(phi.cos(), phi.sin(), 0.0);
        Beam {
            origin: radial * rho + DVec3::Z * s.disk_height_mm,
            dir: (radial * beta.sin() - DVec3::Z * beta.cos()).normalize(),
        }
    }

    /// Inverse kinematics: the axis positions that send the beam's axis via
    /// mirror `l` onto the sample centre (disk angle = the mirror's azimuth,
    /// track = the working position, tilt solved).
    pub fn mirror_axes(&self, l: usize) -> Result<AxisValues, GeometryError> {
        let m = self.mirrors.get(l).ok_or(GeometryError::NoMirror(l, self.mirrors.len()))?;
        let s = &self.source;
        let image = m.reflect_point(DVec3::ZERO); // F1 mirrored: every valid beam passes it
        let phi = image.y.atan2(image.x);
        let radial = DVec3::new(phi.cos(), phi.sin(), 0.0);
        let origin = radial * (s.working_track_mm + s.track_zero_mm) + DVec3::Z * s.disk_height_mm;
        let dir = (image - origin).normalize();
        // The fold mirror turns the beam in the radial plane only.
        let off_plane = dir.dot(DVec3::Z.cross(radial));
        if off_plane.abs() > 1e-6 {
            return Err(GeometryError::Unreachable(
                l,
                format!(
                    "mirror image of the sample is {off_plane:.2e} off the disk's radial plane"
                ),
            ));
        }
        let beta = dir.dot(radial).atan2(-dir.z);
        let axes = AxisValues {
            disk_deg: (phi.to_degrees() - s.disk_zero_deg).rem_euclid(360.0),
            track_mm: s.working_track_mm,
            tilt_deg: beta.to_degrees() / 2.0 - s.tilt_zero_deg,
        };
        // The beam must meet mirror l first, from the front.
        let beam = self.beam(axes);
        let first = self.first_mirror(beam.origin, beam.dir);
        match first {
            Some((k, _)) if k == l => {}
            Some((k, _)) => {
                return Err(GeometryError::Unreachable(
                    l,
                    format!("the beam meets mirror {k} first"),
                ));
            }
            None => {
                return Err(GeometryError::Unreachable(l, "the beam misses every mirror".into()));
            }
        }
        Ok(axes)
    }

    /// The device's mirror table: per mirror, the inverse kinematics'
    /// axis positions in steps under the device's axis configurations.
    pub fn mirror_table(
        &self,
        axes: &[protocol::AxisConfig; 3],
    ) -> Result<Vec<protocol::MirrorPosition>, GeometryError> {
        (0..self.mirrors.len())
            .map(|l| {
                let steps = self
                    .mirror_axes(l)?
                    .to_steps(axes)
                    .map_err(|e| GeometryError::OutOfTravel(l, e))?;
                Ok(protocol::MirrorPosition { steps })
            })
            .collect()
    }

    /// The first mirror a ray meets: (index, point).
    pub fn first_mirror(&self, origin: DVec3, dir: DVec3) -> Option<(usize, DVec3)> {
        self.mirrors
            .iter()
            .enumerate()
            .filter_map(|(l, m)| m.intersect(origin, dir).map(|(t, p)| (t, l, p)))
            .min_by(|a, b| a.0.total_cmp(&b.0))
            .map(|(_, l, p)| (l, p))
    }

    /// Unit direction from the sample centre to mirror `l`'s centre, in the
    /// sample-local frame (z = sample normal): the direction the mirror sees
    /// the sample from and lights it from.
    pub fn mirror_direction(&self, l: usize) -> Option<DVec3> {
        self.mirrors.get(l).map(|m| world_to_sample(m.center().normalize()))
    }

    /// The world point of sample position `uv` ∈ [0, 1]²: u along world
    /// +x, v along world −y (the sample-local +y), uv (0, 0) at the corner
    /// (−size/2, +size/2, 0).
    pub fn sample_point(&self, uv: [f64; 2]) -> DVec3 {
        let (s, h) = (self.sample.size_mm, self.sample.size_mm / 2.0);
        DVec3::new(uv[0] * s - h, h - uv[1] * s, 0.0)
    }

    /// Image point of sample position `uv` seen through mirror `l` (the
    /// pinhole image of its mirror image; None behind the camera).
    pub fn view_point(&self, l: usize, uv: [f64; 2]) -> Option<[f64; 2]> {
        let m = self.mirrors.get(l)?;
        self.camera.project(m.reflect_point(self.sample_point(uv)))
    }

    /// Unit direction from the sample centre towards where the inverse
    /// kinematics' beam meets mirror `l` (sample-local): the nominal light
    /// direction of mirror `l`.
    pub fn light_direction(&self, l: usize) -> Result<DVec3, GeometryError> {
        let beam = self.beam(self.mirror_axes(l)?);
        let m = &self.mirrors[l];
        let (_, p) = m
            .intersect(beam.origin, beam.dir)
            .ok_or_else(|| GeometryError::Unreachable(l, "the beam misses it".into()))?;
        Ok(world_to_sample((p - self.sample_point([0.5, 0.5])).normalize()))
    }

    /// Corners of the sample as the camera sees them through mirror `l`
    /// (image points of the sample's mirror image), for region finding.
    pub fn sample_image_corners(&self, l: usize) -> Option<[[f64; 2]; 4]> {
        let m = self.mirrors.get(l)?;
        let h = self.sample.size_mm / 2.0;
        let mut out = [[0.0; 2]; 4];
        for (k, (x, y)) in [(-h, -h), (h, -h), (h, h), (-h, h)].into_iter().enumerate() {
            out[k] = self.camera.project(m.reflect_point(DVec3::new(x, y, 0.0)))?;
        }
        Some(out)
    }

    /// The same scanner with the sensor binned by `factor` (fewer, larger
    /// pixels; same field of view): the small configuration tests use.
    pub fn with_sensor_scaled(&self, factor: u32) -> ScannerGeometry {
        let mut g = self.clone();
        let k = factor.max(1) as f64;
        g.camera.width = (g.camera.width as f64 / k).round().max(1.0) as u32;
        g.camera.height = (g.camera.height as f64 / k).round().max(1.0) as u32;
        g.camera.focal_px /= k;
        g.camera.principal_px = g.camera.principal_px.map(|p| p / k);
        // The same photons fall on a k² larger pixel.
        g.sensor.sensitivity_e *= k * k;
        g.sensor.full_well_e *= k * k;
        g
    }
}

/// Mirrors on rings about the sample normal, tangent to `ellipsoid`:
/// (polar angle from the normal in degrees, mirrors) per ring, the odd
/// rings staggered by half a mirror; the ellipsoid's points and normals
/// rounded as the shipped file holds them.
fn ring_mirrors(
    ellipsoid: &Ellipsoid,
    rings: &[(f64, usize)],
    size_mm: f64,
    reflectance: f64,
) -> Vec<MirrorSpec> {
    let mut mirrors = Vec::new();
    for (k, &(theta, n)) in rings.iter().enumerate() {
        let theta = theta.to_radians();
        for i in 0..n {
            let stagger = if k % 2 == 1 { 0.5 } else { 0.0 };
            let phi = std::f64::consts::TAU * (i as f64 + stagger) / n as f64;
            let w = DVec3::new(theta.sin() * phi.cos(), theta.sin() * phi.sin(), -theta.cos());
            let c = ellipsoid.point_towards(w);
            mirrors.push(MirrorSpec {
                center_mm: round3(c, 6),
                normal: round3(ellipsoid.inward_normal(c), 12),
                size_mm,
                reflectance,
            });
        }
    }
    mirrors
}

/// `v` rounded to `decimals` places (and without negative zeros), so the
/// shipped file reads cleanly.
fn round3(v: DVec3, decimals: i32) -> [f64; 3] {
    let s = 10f64.powi(decimals);
    v.to_array().map(|x| (x * s).round() / s + 0.0)
}
