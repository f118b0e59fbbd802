//! The suture thread, as a small stochastic model: how much is left, whether it lies across
//! the re-grasp region (hiding the needle, or caught by a closing jaw), whether it tangles.
//! Every probability is a modelling choice, named and documented; the seed's `Thread` stream
//! draws them.

use crate::SimError;
use rand::Rng;
use rand_chacha::ChaCha8Rng;
use serde::{Deserialize, Serialize};

/// The thread model's parameters.
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct ThreadConfig {
    /// Thread length at the start (the paper's threads: 10–40 cm), m.
    pub length_m: f64,
    /// Thread one suture leaves in the tissue (physical: the bite plus the run to the previous
    /// stitch; modelling choice 2 cm), m.
    pub per_suture_m: f64,
    /// Chance that, after an insertion, the thread lies across the re-grasp region
    /// (modelling choice).
    pub p_across_after_insert: f64,
    /// Chance that a sweep clears thread lying across the region (the paper's limitation 2a:
    /// the sweep sometimes misses; modelling choice).
    pub p_sweep_clears: f64,
    /// Chance that a jaw closing where the thread lies catches it (modelling choice).
    pub p_caught_when_across: f64,
    /// Extra chance of lying across per metre of uncinched slack (modelling choice).
    pub p_across_per_m_slack: f64,
    /// Chance that a cinch tangles the thread around a jaw (modelling choice).
    pub p_tangle_per_cinch: f64,
}

impl Default for ThreadConfig {
    fn default() -> Self {
        Self {
            length_m: 0.30,
            per_suture_m: 0.02,
            p_across_after_insert: 0.5,
            p_sweep_clears: 0.85,
            p_caught_when_across: 0.4,
            p_across_per_m_slack: 4.0,
            p_tangle_per_cinch: 0.02,
        }
    }
}

impl ThreadConfig {
    /// Refuse parameters no thread has.
    pub fn validate(&self) -> Result<(), SimError> {
        let bad = |what: &str, v: f64, range: &str| {
            Err(SimError::Config {
                what: format!("thread.{what}"),
                why: format!("{v}; expected {range}"),
            })
        };
        if !(self.length_m.is_finite() && (0.05..=1.0).contains(&self.length_m)) {
            return bad("length_m", self.length_m, "0.05 to 1.0 m");
        }
        if !(self.per_suture_m.is_finite() && (0.0..=0.1).contains(&self.per_suture_m)) {
            return bad("per_suture_m", self.per_suture_m, "0 to 0.1 m");
        }
        for (name, p) in [
            ("p_across_after_insert", self.p_across_after_insert),
            ("p_sweep_clears", self.p_sweep_clears),
            ("p_caught_when_across", self.p_caught_when_across),
            ("p_tangle_per_cinch", self.p_tangle_per_cinch),
        ] {
            if !(p.is_finite() && (0.0..=1.0).contains(&p)) {
                return bad(name, p, "a probability, 0 to 1");
            }
        }
        if !(self.p_across_per_m_slack.is_finite() && self.p_across_per_m_slack >= 0.0) {
            return bad(
                "p_across_per_m_slack",
                self.p_across_per_m_slack,
                "0 or more per metre",
            );
        }
        Ok(())
    }
}

/// The thread's state.
#[derive(Clone, Debug, PartialEq, Serialize)]
pub struct Thread {
    /// Its parameters.
    pub config: ThreadConfig,
    /// Thread left in sutures so far, m.
    pub used_m: f64,
    /// Thread pulled through to the free end by cinching, m.
    pub free_m: f64,
    /// Slack not pulled tight (sutures without a cinch), m.
    pub slack_m: f64,
    /// Whether it lies across the re-grasp region.
    pub across: bool,
    /// Whether a jaw holds it (with or without the needle).
    pub caught: bool,
    /// Whether it is tangled around a jaw.
    pub tangled: bool,
    /// Whether a cinch asked for more than was left.
    pub short: bool,
}

impl Thread {
    /// A fresh thread.
    pub fn new(config: ThreadConfig) -> Result<Self, SimError> {
        config.validate()?;
        Ok(Self {
            config,
            used_m: 0.0,
            free_m: 0.0,
            slack_m: 0.0,
            across: false,
            caught: false,
            tangled: false,
            short: false,
        })
    }

    /// Thread not yet in sutures nor pulled to the free end, m.
    pub fn remaining_m(&self) -> f64 {
        self.config.length_m - self.used_m - self.free_m
    }

    /// A needle passed through the tissue: one suture's worth of thread is used, and the thread
    /// may fall across the re-grasp region (more likely with uncinched slack).
    pub fn on_insertion(&mut self, rng: &mut ChaCha8Rng) {
        self.used_m += self.config.per_suture_m;
        let p = (self.config.p_across_after_insert
            + self.config.p_across_per_m_slack * self.slack_m)
            .clamp(0.0, 1.0);
        self.across = rng.random_bool(p);
    }

    /// A sweep passed over the wound.
    pub fn on_sweep(&mut self, rng: &mut ChaCha8Rng) {
        if self.across && rng.random_bool(self.config.p_sweep_clears) {
            self.across = false;
        }
    }

    /// A jaw closed in the re-grasp region.
    pub fn on_grasp(&mut self, rng: &mut ChaCha8Rng) {
        if self.across && rng.random_bool(self.config.p_caught_when_across) {
            self.caught = true;
        }
    }

    /// The suture is cinched to leave `beta_m` of free thread (β of "Suture Cinching").
    pub fn on_cinch(&mut self, beta_m: f64, rng: &mut ChaCha8Rng) {
        self.slack_m = 0.0;
        self.free_m = beta_m.max(0.0);
        if self.remaining_m() < 0.0 {
            self.short = true;
        }
        if rng.random_bool(self.config.p_tangle_per_cinch) {
            self.tangled = true;
        }
    }

    /// A throw ended without a cinch: its thread stays slack.
    pub fn on_uncinched(&mut self) {
        self.slack_m += self.config.per_suture_m;
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::{Streams, Subsystem};

    #[test]
    fn thread_is_consumed_per_suture_and_a_long_cinch_runs_short() {
        let mut rng = Streams::new(1).rng(Subsystem::Thread);
        let mut t = Thread::new(ThreadConfig {
            length_m: 0.10,
            p_tangle_per_cinch: 0.0,
            ..ThreadConfig::default()
        })
        .expect("thread");
        t.on_insertion(&mut rng);
        t.on_cinch(0.05, &mut rng);
        // 10 cm − 2 cm used − 5 cm free.
        assert!((t.remaining_m() - 0.03).abs() < 1e-12);
        assert!(!t.short);
        t.on_insertion(&mut rng);
        t.on_insertion(&mut rng);
        t.on_cinch(0.05, &mut rng);
        // 10 − 6 − 5 < 0: this cinch asked for more than was left.
        assert!(t.short);
    }

    #[test]
    fn a_sweep_that_always_clears_leaves_nothing_to_catch() {
        let mut rng = Streams::new(2).rng(Subsystem::Thread);
        let config = ThreadConfig {
            p_across_after_insert: 1.0,
            p_sweep_clears: 1.0,
            ..ThreadConfig::default()
        };
        let mut t = Thread::new(config).expect("thread");
        t.on_insertion(&mut rng);
        assert!(t.across);
        t.on_sweep(&mut rng);
        t.on_grasp(&mut rng);
        assert!(!t.across && !t.caught);
        let mut t = Thread::new(ThreadConfig {
            p_caught_when_across: 1.0,
            ..config
        })
        .expect("thread");
        t.on_insertion(&mut rng);
        t.on_grasp(&mut rng);
        assert!(t.caught, "without the sweep the closing jaw catches it");
    }

    #[test]
    fn probabilities_outside_zero_to_one_are_refused() {
        assert!(
            ThreadConfig {
                p_sweep_clears: 1.5,
                ..ThreadConfig::default()
            }
            .validate()
            .is_err()
        );
        assert!(
            ThreadConfig {
                length_m: 2.0,
                ..ThreadConfig::default()
            }
            .validate()
            .is_err()
        );
    }
}
