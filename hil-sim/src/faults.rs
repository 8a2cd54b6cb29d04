//! Seeded, configurable fault injection.
//!
//! A [`FaultPlan`] holds link noise rates (per byte) and scheduled events, each
//! due at a device time or after a number of camera triggers. Plans are plain
//! data: the same plan and seed give the same run. On the command line a
//! fault is written `KIND[:ARGS]@ms=N` or `KIND[:ARGS]@trigger=N`, e.g.
//! `reset@trigger=10`, `disconnect:300@ms=20000`, `lose-steps:disk:400@ms=9000`,
//! `stuck:track:on@ms=0`, `chatter:tilt:0.2@ms=5000`, `switch-ok:tilt@ms=9000`,
//! `driver-fault:on@ms=7000`, `estop:off@ms=8000`, `ignore-trigger:1@trigger=3`,
//! `slow-light:200@ms=0`.

use std::str::FromStr;

use firmware::hal::TICKS_PER_MS;
use protocol::Axis;

use crate::physics::SwitchFault;

/// When a scheduled fault happens.
#[derive(Debug, Clone, Copy, PartialEq)]
pub enum FaultWhen {
    /// At this device tick.
    AtTick(u64),
    /// As soon as this many camera triggers have fired.
    AfterTriggers(u32),
}

/// A fault.
#[derive(Debug, Clone, Copy, PartialEq)]
pub enum FaultEvent {
    /// The link goes away for a while (bytes lost both ways, the host sees a
    /// disconnect), then comes back.
    Disconnect {
        /// How long, ms of device time.
        duration_ms: u64,
    },
    /// The board resets (as if by the watchdog): new boot id, homing lost.
    Reset,
    /// The next `steps` pulses of `axis` do not move it.
    LoseSteps {
        /// Axis.
        axis: Axis,
        /// Steps lost.
        steps: u64,
    },
    /// A switch becomes stuck, chatters, or works again.
    Switch {
        /// Axis.
        axis: Axis,
        /// Its new fault state.
        fault: SwitchFault,
    },
    /// The driver-fault input changes.
    DriverFault(bool),
    /// The emergency-stop input changes.
    EmergencyStop(bool),
    /// The camera ignores the next `n` triggers.
    IgnoreTriggers(u32),
    /// From now on the light's driver loses `edge_ns` of light at every
    /// PWM pulse (slow edges): a dimmed light gives less than its duty
    /// (see [`crate::camera::light_output`]); 0 mends it.
    SlowLight {
        /// Light lost per PWM pulse, ns.
        edge_ns: u32,
    },
}

/// Link noise and scheduled faults.
#[derive(Debug, Clone, Default, PartialEq)]
pub struct FaultPlan {
    /// Probability that a byte on the link has one bit flipped.
    pub corrupt_rate: f64,
    /// Probability that a byte on the link is lost.
    pub drop_rate: f64,
    events: Vec<(FaultWhen, FaultEvent)>,
    link_events: Vec<(u64, FaultEvent)>,
}

impl FaultPlan {
    /// No faults.
    pub fn none() -> FaultPlan {
        FaultPlan::default()
    }

    /// With per-byte corruption probability `rate`.
    pub fn corrupt(mut self, rate: f64) -> FaultPlan {
        self.corrupt_rate = rate;
        self
    }

    /// With per-byte loss probability `rate`.
    pub fn drop_bytes(mut self, rate: f64) -> FaultPlan {
        self.drop_rate = rate;
        self
    }

    /// With `event` at `ms` of device time.
    pub fn at_ms(self, ms: u64, event: FaultEvent) -> FaultPlan {
        self.with(FaultWhen::AtTick(ms * TICKS_PER_MS), event)
    }

    /// With `event` after `n` camera triggers.
    pub fn after_triggers(self, n: u32, event: FaultEvent) -> FaultPlan {
        self.with(FaultWhen::AfterTriggers(n), event)
    }

    /// With `event` when `when` says.
    pub fn with(mut self, when: FaultWhen, event: FaultEvent) -> FaultPlan {
        self.events.push((when, event));
        self
    }

    /// Scheduled events not yet applied.
    pub fn pending(&self) -> &[(FaultWhen, FaultEvent)] {
        &self.events
    }

    /// Earliest pending time-scheduled event.
    pub(crate) fn next_at(&self, _triggers: u32) -> Option<FaultWhen> {
        self.events
            .iter()
            .filter_map(|(w, _)| match w {
                FaultWhen::AtTick(t) => Some(*t),
                FaultWhen::AfterTriggers(_) => None,
            })
            .min()
            .map(FaultWhen::AtTick)
    }

    /// Remove and return one event that is due.
    pub(crate) fn take_due(&mut self, now: u64, triggers: u32) -> Option<FaultEvent> {
        let i = self.events.iter().position(|(w, _)| match *w {
            FaultWhen::AtTick(t) => t <= now,
            FaultWhen::AfterTriggers(n) => triggers >= n,
        })?;
        Some(self.events.remove(i).1)
    }

    pub(crate) fn push_link_event(&mut self, now: u64, event: FaultEvent) {
        self.link_events.push((now, event));
    }

    pub(crate) fn take_link_events(&mut self) -> Vec<(u64, FaultEvent)> {
        std::mem::take(&mut self.link_events)
    }
}

/// A fault as written on the command line.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct FaultSpec {
    /// When.
    pub when: FaultWhen,
    /// What.
    pub event: FaultEvent,
}

/// A fault specification that does not parse.
#[derive(Debug, Clone, PartialEq, Eq, thiserror::Error)]
#[error("bad fault `{spec}`: {why} (expected KIND[:ARGS]@ms=N or KIND[:ARGS]@trigger=N)")]
pub struct FaultSpecError {
    spec: String,
    why: &'static str,
}

fn parse_axis(s: &str) -> Option<Axis> {
    Axis::ALL.into_iter().find(|a| a.name() == s)
}

fn parse_on_off(s: &str) -> Option<bool> {
    match s {
        "on" => Some(true),
        "off" => Some(false),
        _ => None,
    }
}

impl FromStr for FaultSpec {
    type Err = FaultSpecError;

    fn from_str(spec: &str) -> Result<Self, Self::Err> {
        let err = |why| FaultSpecError { spec: spec.to_string(), why };
        let (what, when) = spec.split_once('@').ok_or_else(|| err("missing @"))?;
        let when = match when.split_once('=') {
            Some(("ms", n)) => FaultWhen::AtTick(
                n.parse::<u64>().map_err(|_| err("bad ms"))?.saturating_mul(TICKS_PER_MS),
            ),
            Some(("trigger", n)) => {
                FaultWhen::AfterTriggers(n.parse().map_err(|_| err("bad trigger count"))?)
            }
            _ => return Err(err("bad time")),
        };
        let parts: Vec<&str> = what.split(':').collect();
        let axis =
            |i: usize| parts.get(i).and_then(|s| parse_axis(s)).ok_or_else(|| err("bad axis"));
        let event = match parts[0] {
            "reset" => FaultEvent::Reset,
            "disconnect" => FaultEvent::Disconnect {
                duration_ms: parts
                    .get(1)
                    .and_then(|s| s.parse().ok())
                    .ok_or_else(|| err("bad duration"))?,
            },
            "lose-steps" => FaultEvent::LoseSteps {
                axis: axis(1)?,
                steps: parts
                    .get(2)
                    .and_then(|s| s.parse().ok())
                    .ok_or_else(|| err("bad step count"))?,
            },
            "stuck" => FaultEvent::Switch {
                axis: axis(1)?,
                fault: SwitchFault::Stuck(
                    parts.get(2).and_then(|s| parse_on_off(s)).ok_or_else(|| err("on or off"))?,
                ),
            },
            "chatter" => FaultEvent::Switch {
                axis: axis(1)?,
                fault: SwitchFault::Chatter(
                    parts
                        .get(2)
                        .and_then(|s| s.parse::<f64>().ok())
                        .filter(|p| (0.0..=1.0).contains(p))
                        .ok_or_else(|| err("bad probability"))?,
                ),
            },
            "switch-ok" => FaultEvent::Switch { axis: axis(1)?, fault: SwitchFault::None },
            "driver-fault" => FaultEvent::DriverFault(
                parts.get(1).and_then(|s| parse_on_off(s)).ok_or_else(|| err("on or off"))?,
            ),
            "estop" => FaultEvent::EmergencyStop(
                parts.get(1).and_then(|s| parse_on_off(s)).ok_or_else(|| err("on or off"))?,
            ),
            "slow-light" => FaultEvent::SlowLight {
                edge_ns: parts
                    .get(1)
                    .and_then(|s| s.parse().ok())
                    .ok_or_else(|| err("bad edge loss, ns"))?,
            },
            "ignore-trigger" => FaultEvent::IgnoreTriggers(
                parts.get(1).and_then(|s| s.parse().ok()).ok_or_else(|| err("bad count"))?,
            ),
            _ => return Err(err("unknown kind")),
        };
        Ok(FaultSpec { when, event })
    }
}
