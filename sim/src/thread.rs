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
    /// Thread one tight suture holds (physical: the bite plus the run to the previous
    /// stitch; modelling choice 2 cm), m.
    pub per_suture_m: f64,
    /// Slack a new suture's loop holds until it is cinched (modelling choice 3 cm), m.
    pub loop_per_suture_m: f64,
    /// Free thread the needle needs to make the next throw (modelling choice 5 cm), m.
    pub reach_m: f64,
    /// Chance that, after an insertion, the thread lies across the re-grasp region
    /// (modelling choice).
    pub p_across_after_insert: f64,
    /// Chance that a sweep clears thread lying across the region (the paper's limitation 2a:
    /// the sweep sometimes misses; modelling choice).
    pub p_sweep_clears: f64,
    /// Chance that a jaw closing where the thread lies catches it (modelling choice).
    pub p_caught_when_across: f64,
    /// Extra chance of lying across per metre of slack in loops (modelling choice).
    pub p_across_per_m_slack: f64,
    /// Chance that a cinch tangles the thread around a jaw (modelling choice).
    pub p_tangle_per_cinch: f64,
}

impl Default for ThreadConfig {
    fn default() -> Self {
        Self {
            length_m: 0.30,
            per_suture_m: 0.02,
            loop_per_suture_m: 0.03,
            reach_m: 0.05,
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
        for (name, v) in [
            ("per_suture_m", self.per_suture_m),
            ("loop_per_suture_m", self.loop_per_suture_m),
            ("reach_m", self.reach_m),
        ] {
            if !(v.is_finite() && (0.0..=0.2).contains(&v)) {
                return bad(name, v, "0 to 0.2 m");
            }
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

/// The thread's state. Its tail is anchored at the first stitch; every suture holds some
/// thread tight and, until cinched, a loop of slack; what is left is free on the needle's
/// side. Cinching pulls slack out of the loops into the free length: pull too little early
/// and later throws run out (the paper's limitation 2b).
#[derive(Clone, Debug, PartialEq, Serialize)]
pub struct Thread {
    /// Its parameters.
    pub config: ThreadConfig,
    /// Thread held tight in sutures, m.
    pub used_m: f64,
    /// Slack in the sutures' loops, m.
    pub loop_m: f64,
    /// Whether it lies across the re-grasp region.
    pub across: bool,
    /// Whether a jaw holds it (with or without the needle).
    pub caught: bool,
    /// Whether it is tangled around a jaw.
    pub tangled: bool,
    /// Whether too little is free for the throw under way.
    pub short: bool,
}

impl Thread {
    /// A fresh thread, all of it free.
    pub fn new(config: ThreadConfig) -> Result<Self, SimError> {
        config.validate()?;
        Ok(Self {
            config,
            used_m: 0.0,
            loop_m: 0.0,
            across: false,
            caught: false,
            tangled: false,
            short: false,
        })
    }

    /// Free thread on the needle's side, m.
    pub fn remaining_m(&self) -> f64 {
        self.config.length_m - self.used_m - self.loop_m
    }

    /// A needle passed through the tissue: one more suture holds thread, with a loop of
    /// slack; the thread may fall across the re-grasp region (more likely with more slack).
    /// If less than the reach is left free, the thread is short.
    pub fn on_insertion(&mut self, rng: &mut ChaCha8Rng) {
        self.used_m += self.config.per_suture_m;
        self.loop_m += self.config.loop_per_suture_m;
        // A micrometre of slack for rounding: lengths are sums of centimetres.
        if self.remaining_m() < self.config.reach_m - 1e-6 {
            self.short = true;
        }
        let p = (self.config.p_across_after_insert
            + self.config.p_across_per_m_slack * self.loop_m)
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

    /// A cinch pulled `beta_m` (β of "Suture Cinching"): as much slack as the loops hold
    /// comes out into the free length.
    pub fn on_cinch(&mut self, beta_m: f64, rng: &mut ChaCha8Rng) {
        let pulled = beta_m.max(0.0).min(self.loop_m);
        self.loop_m -= pulled;
        if rng.random_bool(self.config.p_tangle_per_cinch) {
            self.tangled = true;
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::{Streams, Subsystem};

    fn quiet() -> ThreadConfig {
        ThreadConfig {
            p_across_after_insert: 0.0,
            p_across_per_m_slack: 0.0,
            p_tangle_per_cinch: 0.0,
            ..ThreadConfig::default()
        }
    }

    #[test]
    fn cinching_pulls_loop_slack_back_to_the_free_end() {
        let mut rng = Streams::new(1).rng(Subsystem::Thread);
        let mut t = Thread::new(quiet()).expect("thread");
        t.on_insertion(&mut rng);
        // 30 cm − 2 cm tight − 3 cm loop.
        assert!((t.remaining_m() - 0.25).abs() < 1e-12);
        t.on_cinch(0.12, &mut rng);
        // β = 12 cm pulls the whole 3 cm loop out, no more.
        assert!((t.remaining_m() - 0.28).abs() < 1e-12);
        assert!(!t.short);
    }

    #[test]
    fn without_cinching_the_sixth_throw_runs_short() {
        let mut rng = Streams::new(1).rng(Subsystem::Thread);
        let mut t = Thread::new(quiet()).expect("thread");
        for throw in 1..=6 {
            t.on_insertion(&mut rng);
            // Free: 30 − 5·throw cm; short once below the 5 cm reach.
            assert_eq!(
                t.short,
                throw == 6,
                "throw {throw}: {} m free",
                t.remaining_m()
            );
        }
        let mut t = Thread::new(quiet()).expect("thread");
        for _ in 1..=6 {
            t.on_insertion(&mut rng);
            t.on_cinch(0.03, &mut rng);
        }
        assert!(!t.short, "cinched every throw: 30 − 6·2 = 18 cm free");
        assert!((t.remaining_m() - 0.18).abs() < 1e-12);
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
