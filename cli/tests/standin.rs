//! Against a DDS that is not ours: a dVRK 2.x console stand-in on Cyclone DDS
//! (`dvrk/standin/dvrk_standin.py`, its Python environment made by `tests/python/setup.sh`)
//! with the console's QoS and arm state machine. Connects that must not lose their first
//! command, an old latched error that must not fail a new run, an error during the run that
//! must, and a whole `--no-simulator` mission.
#![cfg(feature = "ros2")]

mod support;

use std::time::{Duration, Instant};
use stitch_dvrk::arm::{DvrkConfig, Ros2Dvrk};
use stitch_dvrk::ros2::Ros2Options;
use stitch_robot::{Arm, Pose};
use support::{SimNode, StandIn, hand_eye_config, real_args, run, serial, tmp};

/// A domain of this test's own, above the ranges the other ROS 2 tests use.
fn domain(k: u16) -> u16 {
    216 + k
}

fn percentile(sorted: &[f64], p: f64) -> f64 {
    let i = ((sorted.len() as f64 - 1.0) * p).round() as usize;
    sorted[i.min(sorted.len() - 1)]
}

/// Connect `n` times (a fresh DDS participant each time, as a new `stitch run` is), half of
/// them to a freshly started console (first command `enable`) and half to one left enabled
/// and homed by a previous run (first command `trajectory_j/set_ratio`): every connect
/// succeeds and leaves both arms enabled, homed and at the configured speed ratio.
#[test]
fn connects_lose_no_first_command() {
    let _one = serial();
    let n: usize = std::env::var("STITCH_STANDIN_CONNECTS")
        .ok()
        .and_then(|v| v.parse().ok())
        .unwrap_or(30);
    let d = domain(0);
    let mut standin = StandIn::start(d, &[]);
    let config = DvrkConfig::default();
    let ros = Ros2Options { domain_id: d };
    let mut times = Vec::new();
    let mut resent = 0;
    for i in 0..n {
        let fresh = i % 2 == 0;
        assert_eq!(
            standin.ask(if fresh {
                "reset disabled"
            } else {
                "reset homed"
            }),
            "ok"
        );
        let t = Instant::now();
        let dvrk = match Ros2Dvrk::connect(&ros, &config) {
            Ok(d) => d,
            Err(e) => panic!(
                "connect {i} (fresh console: {fresh}): {e}\nstand-in: {}",
                standin.status()
            ),
        };
        times.push(t.elapsed().as_secs_f64());
        resent += usize::from(dvrk.resends() > 0);
        let status = standin.status();
        for arm in ["PSM1", "PSM2"] {
            let a = &status[arm];
            assert_eq!(a["state"], "ENABLED", "connect {i}, {arm}: {a}");
            assert_eq!(a["homed"], true, "connect {i}, {arm}: {a}");
            assert_eq!(
                a["ratio"].as_f64(),
                Some(config.speed_ratio),
                "connect {i}, {arm}: set_ratio lost: {a}"
            );
        }
        drop(dvrk);
    }
    times.sort_by(f64::total_cmp);
    eprintln!(
        "{n} connects against the Cyclone DDS stand-in: 0 lost first commands, {resent} \
         needed a resend; time to connect median {:.3} s, p99 {:.3} s, max {:.3} s",
        percentile(&times, 0.5),
        percentile(&times, 0.99),
        times[times.len() - 1]
    );
}

/// A small move of arm `i` from where it is.
fn nudge(dvrk: &Ros2Dvrk, i: usize) -> Result<(), stitch_robot::RobotError> {
    let arm = dvrk.arm(i).expect("arm");
    let here = arm.measured_cp()?;
    let goal = Pose::from_parts(
        (here.translation.vector + stitch_robot::nalgebra::Vector3::new(0.0, 0.0, 0.005)).into(),
        here.rotation,
    );
    arm.move_cp(&goal)?.wait(Duration::from_secs(10))
}

#[test]
fn every_first_command_lost_is_sent_again_and_confirmed() {
    let _one = serial();
    let d = domain(4);
    // A console whose command readers each drop the first sample they take, as a reader
    // that did not know the writer yet does.
    let mut standin = StandIn::start(d, &["--lose-first"]);
    let dvrk = Ros2Dvrk::connect(&Ros2Options { domain_id: d }, &DvrkConfig::default())
        .expect("the lost enable and set_ratio are sent again");
    nudge(&dvrk, 0).expect("PSM1's lost first move_cp is sent again");
    nudge(&dvrk, 1).expect("PSM2's too");
    let status = standin.status();
    for arm in ["PSM1", "PSM2"] {
        let a = &status[arm];
        assert_eq!(a["state"], "ENABLED", "{arm}: {a}");
        assert_eq!(a["homed"], true, "{arm}: {a}");
        assert_eq!(a["ratio"].as_f64(), Some(0.2), "{arm}: {a}");
        // enable, set_ratio and move_cp each lost once.
        assert_eq!(a["counts"]["lost"].as_u64(), Some(3), "{arm}: {a}");
    }
    assert!(dvrk.resends() >= 6, "resends: {}", dvrk.resends());
}

#[test]
fn a_speed_ratio_the_dvrk_never_confirms_refuses_the_run() {
    let _one = serial();
    let d = domain(5);
    let _standin = StandIn::start(d, &["--ignore", "trajectory_j/set_ratio"]);
    let config = DvrkConfig {
        connect_timeout_s: 3.0,
        ..DvrkConfig::default()
    };
    let e = Ros2Dvrk::connect(&Ros2Options { domain_id: d }, &config)
        .expect_err("a mission at the dVRK's own speed is refused");
    let e = e.to_string();
    assert!(
        e.contains("trajectory_j/set_ratio: not done within 3.0 s, sent 4 time(s)")
            && e.contains("says 1, not 0.2"),
        "{e}"
    );
}

#[test]
fn an_old_latched_error_does_not_fail_a_new_run() {
    let _one = serial();
    let d = domain(1);
    let mut standin = StandIn::start(d, &[]);
    // A previous run: PSM2 faulted; the console latched the error (transient local, depth
    // 100). An operator recovered the arm (enabled, homed, idle); nothing new was published.
    assert_eq!(
        standin.ask("error PSM2 joint 3 following error (an earlier run)"),
        "ok"
    );
    assert_eq!(standin.ask("reset homed"), "ok");
    std::thread::sleep(Duration::from_millis(300));
    let dvrk = Ros2Dvrk::connect(&Ros2Options { domain_id: d }, &DvrkConfig::default())
        .expect("an error from before this run does not fail the connect");
    let ignored = dvrk.ignored_history();
    assert!(
        ignored.iter().any(|e| e.contains("an earlier run")),
        "the old error is said to be ignored, not silently dropped: {ignored:?}"
    );
    nudge(&dvrk, 1).expect("and does not fail PSM2's first motion");
    nudge(&dvrk, 0).expect("nor PSM1's");
}

#[test]
fn an_error_during_the_run_fails_it() {
    let _one = serial();
    let d = domain(2);
    let mut standin = StandIn::start(d, &[]);
    let dvrk =
        Ros2Dvrk::connect(&Ros2Options { domain_id: d }, &DvrkConfig::default()).expect("connect");
    nudge(&dvrk, 1).expect("a motion before the error");
    assert_eq!(standin.ask("error PSM2 joint 3 following error"), "ok");
    std::thread::sleep(Duration::from_millis(200));
    let moves = |s: &mut StandIn| s.status()["PSM2"]["counts"]["move_cp"].as_u64();
    let before = moves(&mut standin);
    let e = nudge(&dvrk, 1).expect_err("the error fails PSM2's next motion");
    assert!(
        e.to_string().contains("joint 3 following error"),
        "the error names what the dVRK said: {e}"
    );
    assert_eq!(
        moves(&mut standin),
        before,
        "nothing is commanded to a faulted arm"
    );
    nudge(&dvrk, 0).expect("PSM1 had no error");
}

/// The mock's arms' homes (`sim/`'s scene), so that the stand-in's arms stand where the
/// camera's rendered jaws and needle are.
const HOMES: [&str; 2] = [
    "PSM1=-0.03,0.0,-0.09,0,0,0,1",
    "PSM2=0.04,0.02,-0.09,0,0,0,1",
];

#[test]
fn a_whole_mission_without_the_simulator_runs_against_the_cyclone_console() {
    let _one = serial();
    let d = domain(3);
    // The arms: the stand-in, on Cyclone DDS. The camera: a sim-node streaming rendered pairs,
    // its own arms on namespaces nobody uses.
    let mut standin = StandIn::start(d, &["--pose", HOMES[0], "--pose", HOMES[1]]);
    let names = tmp("standin-camera.toml");
    std::fs::write(&names, "arms = [\"SIM1\", \"SIM2\"]\n").expect("names");
    let node = SimNode::start(
        &d.to_string(),
        &[
            "--camera-hz",
            "15",
            "--dvrk-config",
            names.to_str().expect("utf-8"),
        ],
    );
    let config = hand_eye_config(&node, 30, "");
    let d = d.to_string();
    let ran = run(
        &real_args(&d, &config),
        &tmp("standin-mission.jsonl"),
        Duration::from_secs(240),
    );
    let status = standin.status();
    assert!(
        matches!(ran.code, Some(0 | 4)),
        "{}\nstand-in: {status}",
        ran.out
    );
    assert!(
        ran.journal
            .contains(r#""primitive":"insert","attempt":0,"outcome":{"result":"succeeded""#),
        "the insertion ran:\n{}",
        ran.journal
    );
    // The right arm inserts and sweeps. The left arm's first motion is the extraction's
    // grasp, which needs the needle seen lodged through the holes; the camera's needle never
    // moves (nothing simulates it: it hangs where the mock's right jaw starts), so the
    // extraction refuses it (a perception dropout, as at a bench) and the left arm is only
    // held. (Until 2026-12-05 a circle fitted freely was taken wherever it lay, and the
    // hanging needle was now and then "found" in the tissue.)
    let c = &status["PSM1"]["counts"];
    assert!(c["move_cp"].as_u64() > Some(0), "PSM1 moved: {status}");
    assert!(
        c["jaw/move_jp"].as_u64() > Some(0),
        "PSM1's jaw moved: {status}"
    );
    assert_eq!(
        status["PSM2"]["counts"]["move_cp"].as_u64(),
        Some(0),
        "PSM2 was not moved: {status}"
    );
    assert!(
        ran.journal.contains(
            r#""primitive":"extract","attempt":0,"outcome":{"result":"failed","kind":"perception_dropout""#
        ),
        "the extraction did not see the needle in tissue:\n{}",
        ran.journal
    );
    for arm in ["PSM1", "PSM2"] {
        let c = &status[arm]["counts"];
        assert_eq!(c["refused"].as_u64(), Some(0), "{arm}: {status}");
        assert_eq!(status[arm]["ratio"].as_f64(), Some(0.2), "{arm}: {status}");
        assert_eq!(status[arm]["busy"], false, "{arm} ended idle: {status}");
        assert!(c["hold"].as_u64() >= Some(1), "{arm} was held: {status}");
    }
    // The camera's needle never moves (nothing simulates it), so the mission fails at an
    // extraction or ends: either way with both arms held and the outcome last.
    assert!(
        ran.journal.contains(r#""event":"hold""#),
        "the run ends holding:\n{}",
        ran.journal
    );
    assert!(
        ran.journal
            .lines()
            .last()
            .is_some_and(|l| l.contains(r#""event":"finished""#)),
        "the journal ends with the outcome:\n{}",
        ran.journal
    );
}
