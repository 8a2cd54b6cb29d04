//! Simulated mechanics: stepper motors that can stall, and home switches with
//! hysteresis that can stick or chatter.
//!
//! Positions are physical micro-steps in the machine's own frame: each axis'
//! switch sits where the configuration the scanner is built with says its
//! `home_position` is (by default TRACK at 0, TILT at −9 333, the DISK
//! index flag at 0 mod 16 000), so after a correct homing the controller's
//! counter equals the physical position.

use firmware::hal::TICK_HZ;
use protocol::Axis;
use rand::Rng;

/// Torque/speed limits of one motor and its load.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct MotorModel {
    /// Above this step rate the motor cannot follow at all (pull-out), steps/s.
    pub pull_out_speed: f64,
    /// A stalled motor re-synchronises once commanded below this, steps/s.
    pub pull_in_speed: f64,
    /// Acceleration the torque allows at standstill, steps/s²; it falls as
    /// `1 − (v / pull_out)²` with speed.
    pub max_accel: f64,
}

impl MotorModel {
    /// Defaults per axis: comfortably above the default axis limits of
    /// spec/hardware.md, so a correct configuration never stalls.
    pub fn default_for(axis: Axis) -> MotorModel {
        let (pull_out, max_accel) = match axis {
            Axis::Disk => (6_000.0, 40_000.0),
            Axis::Track => (80_000.0, 1_200_000.0),
            Axis::Tilt => (8_000.0, 60_000.0),
        };
        MotorModel { pull_out_speed: pull_out, pull_in_speed: pull_out * 0.2, max_accel }
    }

    /// Acceleration available at speed `v`.
    pub fn available_accel(&self, v: f64) -> f64 {
        let r = v / self.pull_out_speed;
        self.max_accel * (1.0 - r * r).max(0.0)
    }
}

/// Steps over which speed and acceleration are estimated: long enough that
/// the ±1 tick quantisation of step times (at 64 000 steps/s, 0.5 % of an
/// interval) does not read as acceleration.
const WINDOW: usize = 64;
/// A gap longer than this between steps means the motor started from rest.
const REST_GAP_TICKS: u64 = TICK_HZ as u64 / 20;

/// One stepper motor: integrates STEP pulses into a physical position unless
/// the commanded motion exceeds what its torque allows.
#[derive(Debug, Clone)]
pub struct SimMotor {
    /// Model limits.
    pub model: MotorModel,
    position: i64,
    /// Ticks of the last `WINDOW * 2 + 1` pulses (ring), newest at `head`.
    ticks: [u64; 2 * WINDOW + 1],
    count: usize,
    stalled: bool,
    lost: u64,
    /// Steps still to be dropped by an injected fault.
    inject_loss: u64,
}

impl SimMotor {
    /// A motor at `position`.
    pub fn new(model: MotorModel, position: i64) -> SimMotor {
        SimMotor {
            model,
            position,
            ticks: [0; 2 * WINDOW + 1],
            count: 0,
            stalled: false,
            lost: 0,
            inject_loss: 0,
        }
    }

    /// Physical position, micro-steps.
    pub fn position(&self) -> i64 {
        self.position
    }

    /// Steps commanded but not performed so far.
    pub fn lost_steps(&self) -> u64 {
        self.lost
    }

    /// Whether the motor is stalled now.
    pub fn is_stalled(&self) -> bool {
        self.stalled
    }

    /// Drop the next `steps` pulses (a fault: slipping belt, skipped teeth).
    pub fn inject_lost_steps(&mut self, steps: u64) {
        self.inject_loss += steps;
    }

    fn tick_back(&self, back: usize) -> u64 {
        let n = self.ticks.len();
        self.ticks[(self.count - 1 - back) % n]
    }

    /// A STEP pulse at `tick` with DIR `positive`; returns whether the rotor moved.
    pub fn pulse(&mut self, tick: u64, positive: bool) -> bool {
        if self.count > 0 && tick.saturating_sub(self.tick_back(0)) > REST_GAP_TICKS {
            self.count = 0; // started again from rest
            self.stalled = false;
        }
        let n = self.ticks.len();
        self.ticks[self.count % n] = tick;
        self.count += 1;

        let hz = TICK_HZ as f64;
        // Speed over the last WINDOW steps and over the WINDOW before them.
        let (v, accel) = if self.count > 2 * WINDOW {
            let (t0, t1, t2) =
                (self.tick_back(2 * WINDOW), self.tick_back(WINDOW), self.tick_back(0));
            let v_old = WINDOW as f64 * hz / (t1 - t0).max(1) as f64;
            let v_new = WINDOW as f64 * hz / (t2 - t1).max(1) as f64;
            (v_new, (v_new - v_old) / ((t2 - t0) as f64 / 2.0 / hz))
        } else if self.count > WINDOW {
            let (t1, t2) = (self.tick_back(WINDOW), self.tick_back(0));
            (WINDOW as f64 * hz / (t2 - t1).max(1) as f64, 0.0)
        } else {
            (0.0, 0.0)
        };
        if self.stalled {
            if v < self.model.pull_in_speed {
                self.stalled = false;
            }
        } else if v > self.model.pull_out_speed
            || accel.abs() > self.model.available_accel(v) * 1.05
        {
            self.stalled = true;
        }
        if self.stalled || self.inject_loss > 0 {
            self.inject_loss = self.inject_loss.saturating_sub(1);
            self.lost += 1;
            return false;
        }
        self.position += if positive { 1 } else { -1 };
        true
    }
}

/// Where a switch is actuated.
#[derive(Debug, Clone, Copy, PartialEq)]
pub enum SwitchGeometry {
    /// A limit switch actuated at positions ≤ `edge`.
    Below {
        /// Actuation edge, micro-steps.
        edge: i64,
    },
    /// A limit switch actuated at positions ≥ `edge`.
    Above {
        /// Actuation edge, micro-steps.
        edge: i64,
    },
    /// A flag `width` wide starting at `edge`, repeating every `rev`.
    Index {
        /// Start of the flag.
        edge: i64,
        /// Flag width.
        width: i64,
        /// Steps per revolution.
        rev: i64,
    },
}

/// An injected switch fault.
#[derive(Debug, Clone, Copy, PartialEq)]
pub enum SwitchFault {
    /// Works.
    None,
    /// Reads actuated (or released) whatever the position.
    Stuck(bool),
    /// Toggles at random with this probability per sample.
    Chatter(f64),
}

/// A home or index switch with hysteresis.
#[derive(Debug, Clone)]
pub struct SimSwitch {
    /// Where it is.
    pub geometry: SwitchGeometry,
    /// Extra travel needed to release it, micro-steps.
    pub hysteresis: i64,
    /// Injected fault.
    pub fault: SwitchFault,
    state: bool,
}

impl SimSwitch {
    /// A working switch.
    pub fn new(geometry: SwitchGeometry, hysteresis: i64) -> SimSwitch {
        SimSwitch { geometry, hysteresis, fault: SwitchFault::None, state: false }
    }

    /// The default switch of `axis` (spec/hardware.md).
    pub fn default_for(axis: Axis) -> SimSwitch {
        SimSwitch::built_for(axis, &protocol::default_axes()[axis.index()])
    }

    /// The switch of `axis` on a scanner built with the drive `config`
    /// describes: its edge where homing in the configured direction meets
    /// it at `home_position`; the default's flag width and hysteresis
    /// (4.5° of the disk; 0.01 mm, 0.0375°, 0.09° of travel) in its steps.
    pub fn built_for(axis: Axis, config: &protocol::AxisConfig) -> SimSwitch {
        let default = protocol::default_axes()[axis.index()];
        let scale = config.steps_per_unit as f64 / default.steps_per_unit as f64;
        let hysteresis = |h: f64| ((h * scale).round() as i64).max(1);
        let home = config.homing.home_position as i64;
        let positive = config.homing.direction == protocol::Direction::Positive;
        match axis {
            Axis::Disk => {
                let rev = config.steps_per_rev.max(1) as i64;
                let width = ((200 * rev) as f64 / 16_000.0).round().max(1.0) as i64;
                // Homing meets the flag's lower edge going up, its upper one
                // going down.
                let edge = if positive { home } else { home - width };
                SimSwitch::new(SwitchGeometry::Index { edge, width, rev }, hysteresis(4.0))
            }
            Axis::Track | Axis::Tilt => {
                let h = if axis == Axis::Track { 16.0 } else { 10.0 };
                let geometry = if positive {
                    SwitchGeometry::Above { edge: home }
                } else {
                    SwitchGeometry::Below { edge: home }
                };
                SimSwitch::new(geometry, hysteresis(h))
            }
        }
    }

    /// Whether the mechanism actuates it at `position` (no fault, with
    /// hysteresis relative to the current state).
    fn mechanically(&self, position: i64) -> bool {
        let h = if self.state { self.hysteresis } else { 0 };
        match self.geometry {
            SwitchGeometry::Below { edge } => position <= edge + h,
            SwitchGeometry::Above { edge } => position >= edge - h,
            SwitchGeometry::Index { edge, width, rev } => {
                let p = (position - edge + h).rem_euclid(rev);
                p < width + 2 * h
            }
        }
    }

    /// Sample the switch at `position`.
    pub fn sample(&mut self, position: i64, rng: &mut impl Rng) -> bool {
        self.state = self.mechanically(position);
        match self.fault {
            SwitchFault::None => self.state,
            SwitchFault::Stuck(level) => level,
            SwitchFault::Chatter(p) => {
                if rng.random_bool(p.clamp(0.0, 1.0)) {
                    !self.state
                } else {
                    self.state
                }
            }
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_default_drives_place_the_spec_switches() {
        let switch = |axis| {
            let s = SimSwitch::default_for(axis);
            (s.geometry, s.hysteresis)
        };
        assert_eq!(
            switch(Axis::Disk),
            (SwitchGeometry::Index { edge: 0, width: 200, rev: 16_000 }, 4)
        );
        assert_eq!(switch(Axis::Track), (SwitchGeometry::Below { edge: 0 }, 16));
        assert_eq!(switch(Axis::Tilt), (SwitchGeometry::Below { edge: -9_333 }, 10));
    }

    #[test]
    fn other_drives_place_their_switches_where_homing_meets_them() {
        let mut rng = <rand_chacha::ChaCha8Rng as rand::SeedableRng>::seed_from_u64(1);
        // A tilt twice as fine, homed going up to +35°.
        let mut tilt = protocol::default_axes()[2];
        tilt.steps_per_unit *= 2.0;
        tilt.homing.direction = protocol::Direction::Positive;
        tilt.homing.home_position = 18_667;
        let mut s = SimSwitch::built_for(Axis::Tilt, &tilt);
        assert_eq!((s.geometry, s.hysteresis), (SwitchGeometry::Above { edge: 18_667 }, 20));
        assert!(!s.sample(18_666, &mut rng) && s.sample(18_667, &mut rng));
        // Released only 20 steps below the edge.
        assert!(s.sample(18_648, &mut rng) && !s.sample(18_646, &mut rng));
        // A disk of 32 000 steps a turn homed going down meets the flag's
        // upper edge at its home position.
        let mut disk = protocol::default_axes()[0];
        disk.steps_per_unit *= 2.0;
        disk.steps_per_rev = 32_000;
        disk.homing.direction = protocol::Direction::Negative;
        let mut s = SimSwitch::built_for(Axis::Disk, &disk);
        assert_eq!(s.geometry, SwitchGeometry::Index { edge: -400, width: 400, rev: 32_000 });
        assert!(!s.sample(1, &mut rng) && s.sample(31_999, &mut rng));
    }
}
