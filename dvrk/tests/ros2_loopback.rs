//! Our messages through real DDS: a `measured_cp` PoseStamped published by one ROS 2
//! participant arrives, equal, at another, on this test's own domain id.
#![cfg(feature = "ros2")]

use futures::StreamExt;
use ros2_client::{MessageTypeName, Name, NodeName, NodeOptions};
use std::time::Duration;
use stitch_dvrk::msg::*;
use stitch_dvrk::ros2::{Ros2Options, context, stream_qos};

#[test]
fn a_pose_crosses_dds_between_two_participants() {
    // A domain of its own, away from 0 and from other test runs.
    let options = Ros2Options {
        domain_id: 100 + (std::process::id() % 100) as u16,
    };
    let (ca, cb) = (context(&options).expect("a"), context(&options).expect("b"));
    let node = |c: &ros2_client::Context, n: &str| {
        c.new_node(
            NodeName::new("/stitch_test", n).expect("name"),
            NodeOptions::new(),
        )
        .expect("node")
    };
    let (mut a, mut b) = (node(&ca, "dvrk"), node(&cb, "stitch"));
    let ex = smol::Executor::new();
    ex.spawn(a.spinner().expect("spinner").spin()).detach();
    ex.spawn(b.spinner().expect("spinner").spin()).detach();
    let name = Name::new("/PSM1", "measured_cp").expect("topic name");
    let ty = MessageTypeName::new("geometry_msgs", "PoseStamped");
    let ta = a
        .create_topic(&name, ty.clone(), &stream_qos())
        .expect("topic");
    let tb = b.create_topic(&name, ty, &stream_qos()).expect("topic");
    let publisher = a
        .create_publisher::<PoseStamped>(&ta, None)
        .expect("publisher");
    let subscription = b
        .create_subscription::<PoseStamped>(&tb, None)
        .expect("subscription");
    let sent = PoseStamped {
        header: Header {
            stamp: Time {
                sec: 1_700_000_000,
                nanosec: 5,
            },
            frame_id: "PSM1_base".into(),
        },
        pose: Pose {
            position: Point {
                x: 0.01,
                y: -0.02,
                z: -0.09,
            },
            orientation: Quaternion::default(),
        },
    };
    let got = smol::future::block_on(ex.run(async {
        let timeout = |s| async_io::Timer::after(Duration::from_secs(s));
        // A message sent before the subscriber matched would be lost: wait for it.
        let matched = smol::future::or(
            async {
                publisher.wait_for_subscription(&a).await;
                true
            },
            async {
                timeout(20).await;
                false
            },
        )
        .await;
        assert!(matched, "no subscriber matched within 20 s");
        publisher
            .async_publish(sent.clone())
            .await
            .expect("published");
        let stream = subscription.async_stream();
        futures::pin_mut!(stream);
        smol::future::or(
            async { stream.next().await.map(|r| r.map(|(m, _)| m)) },
            async {
                timeout(20).await;
                None
            },
        )
        .await
    }));
    let got = got.expect("a message within 20 s").expect("decoded");
    assert_eq!(got, sent);
}

/// A simulator whose replies cannot be read: the call fails, and says so, instead of only
/// "did not answer" (the replies used to be dropped without a word).
#[test]
fn an_oracle_call_answered_only_with_unreadable_replies_names_them() {
    use std::sync::{Arc, Mutex};
    use stitch_dvrk::oracle::{Oracle, REPLY_TOPIC, REQUEST_TOPIC};
    use stitch_dvrk::ros2::{Bus, types};
    let options = Ros2Options {
        domain_id: 200 + (std::process::id() % 30) as u16,
    };
    let mut fake = Bus::new(&options, "garbled_sim").expect("the fake simulator's bus");
    let reply = Arc::new(Mutex::new(
        fake.publisher::<StringMsg>(REPLY_TOPIC, types::STRING, &stream_qos())
            .expect("reply topic"),
    ));
    let out = Arc::clone(&reply);
    fake.subscribe::<StringMsg, _>(REQUEST_TOPIC, types::STRING, &stream_qos(), move |_| {
        let _ = out.lock().expect("reply").publish(StringMsg {
            data: "{\"client\": 1, \"seq\": ".into(),
        });
    })
    .expect("request topic");
    let e =
        Oracle::connect(&options, Duration::from_secs(4)).expect_err("nothing readable came back");
    assert!(
        e.contains("did not answer Ping") && e.contains("could not be read"),
        "{e}"
    );
}
