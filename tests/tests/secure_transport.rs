//! Robots over zenoh with mutual TLS and the server's access rules, on loopback: a robot with
//! the site's certificate streams; one without a certificate, one whose certificate another
//! authority signed, and one publishing under another robot's id are refused by zenoh before
//! ingest, and the server never hears of them.

use std::path::Path;
use std::time::Duration;
use vsgraphs_sdk::robot::now_ns;
use vsgraphs_sdk::zenoh_config::TlsSettings;
use vsgraphs_sdk::{Delivery, Robot, RobotConfig};
use vsgraphs_server::certificates;
use vsgraphs_tests::*;
use vsgraphs_vision::dictionary::MarkerDictionary;
use vsgraphs_vision::synth::render;

/// Robot `id` connecting to `endpoint` with `tls`; `None` if zenoh refuses to open.
async fn robot(id: &str, endpoint: &str, tls: TlsSettings) -> Option<Robot> {
    let mut config = RobotConfig::connecting_to(id, endpoint);
    config.zenoh.tls = tls;
    config.delivery = Delivery::Reliable;
    Robot::connect(config).await.ok()
}

type Frame = (
    vsgraphs_proto::CameraModel,
    vsgraphs_proto::ColourImage,
    vsgraphs_proto::DepthImage,
);

async fn publish(
    robot: &Robot,
    (camera, colour, depth): &Frame,
) -> Result<(u64, usize), vsgraphs_sdk::RobotError> {
    robot
        .publish(
            now_ns(),
            camera.clone(),
            1000.0,
            colour.clone(),
            depth.clone(),
        )
        .await
}

fn tls(dir: &Path, ca: &str, name: Option<&str>) -> TlsSettings {
    TlsSettings {
        root_ca_certificate: dir.join(ca),
        certificate: name
            .map(|n| dir.join(format!("{n}.pem")))
            .unwrap_or_default(),
        private_key: name
            .map(|n| dir.join(format!("{n}-key.pem")))
            .unwrap_or_default(),
        mutual: name.is_some(),
    }
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn only_robots_of_the_site_publish_and_only_under_their_own_ids() {
    assert_eq!(refusals(true).await, ["good"]);
}

/// Without the access rules, mutual TLS alone keeps out the robots without a certificate of
/// the site, but not a robot of the site publishing under another's id.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn mutual_tls_alone_refuses_robots_without_a_certificate_of_the_site() {
    assert_eq!(refusals(false).await, ["good", "other"]);
}

/// A good robot streams, then an impostor (the good robot's certificate, another robot's id),
/// a robot without a certificate and one certified by another authority publish, with the
/// access rules (`acl`) or without: the robots the server heard of.
async fn refusals(acl: bool) -> Vec<String> {
    let dir = tempfile::tempdir().unwrap();
    let site = dir.path().join("site");
    let robots = ["good".to_owned(), "other".to_owned()];
    certificates::make(&site, &["127.0.0.1".into()], &robots).unwrap();
    // Another site's authority, with a certificate for a robot of the same name.
    let foreign = dir.path().join("foreign");
    certificates::make(&foreign, &[], &["other".into()]).unwrap();

    let endpoint = format!("tls/127.0.0.1:{}", free_port());
    let test = TestServer::start_with(|c| {
        c.zenoh.listen = vec![endpoint.clone()];
        c.zenoh.tls = TlsSettings {
            mutual: true,
            ..tls(&site, "ca.pem", Some("server"))
        };
        if acl {
            c.ingest.allowed_robots = robots.to_vec();
        }
    })
    .await;

    let camera = d435();
    let dictionary = MarkerDictionary::predefined("DICT_4X4_100").unwrap();
    let rendered = render(&camera, &dictionary, &[], 2.0).unwrap();
    let (colour, depth) = encode_rendered(&camera, &rendered);
    let frame = (camera.to_wire(), colour, depth);
    let received = |id: &'static str| {
        let client = test.client.clone();
        async move { client.robot(id).await.ok().map(|s| s.frames.received) }
    };

    let good = robot("good", &endpoint, tls(&site, "ca.pem", Some("robot-good")))
        .await
        .expect("a robot of the site connects");
    publish(&good, &frame).await.unwrap();
    wait_for(
        "the good robot's frame",
        Duration::from_secs(30),
        || async { received("good").await.filter(|&n| n >= 1) },
    )
    .await;

    // A robot of the site publishing as another robot of the site; one without a certificate;
    // one whose certificate another authority signed.
    let impostor = robot("other", &endpoint, tls(&site, "ca.pem", Some("robot-good"))).await;
    let uncertified = robot("nobody", &endpoint, tls(&site, "ca.pem", None)).await;
    let foreign_robot = robot(
        "stranger",
        &endpoint,
        tls(&foreign, "../site/ca.pem", Some("robot-other")),
    )
    .await;
    let mut tried = 0;
    for robot in [&impostor, &uncertified, &foreign_robot]
        .into_iter()
        .flatten()
    {
        tried += 1;
        // A refused connection may fail to publish or publish into nothing: both are refusals.
        let _ = publish(robot, &frame).await;
    }
    // The good robot's next frame arrives after theirs were sent: by then they would have too.
    publish(&good, &frame).await.unwrap();
    wait_for(
        "the good robot's second frame",
        Duration::from_secs(30),
        || async { received("good").await.filter(|&n| n >= 2) },
    )
    .await;
    tokio::time::sleep(Duration::from_millis(500)).await;
    let heard: Vec<String> = test
        .client
        .robots()
        .await
        .unwrap()
        .into_iter()
        .map(|r| r.robot_id)
        .collect();
    // The good robot's liveliness passes the rules too, and it sees the server's.
    assert_eq!(
        test.client.robot("good").await.unwrap().presence,
        vsgraphs_proto::api::Presence::Online
    );
    wait_for("the server seen", Duration::from_secs(10), || async {
        good.server_online().then_some(())
    })
    .await;
    eprintln!(
        "access rules {acl}: {tried} robots opened a zenoh session; the server heard of {heard:?}"
    );
    for robot in [impostor, uncertified, foreign_robot].into_iter().flatten() {
        let _ = robot.close().await;
    }
    good.close().await.unwrap();
    heard
}

/// A ROS 2 robot under the access rules: its router's certificate names it, the server's
/// subscriptions to its topics reach it, and what it puts on them is counted as its input; a
/// robot of the site with another certificate putting on the same keys is refused by zenoh.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_ros_robot_puts_on_its_topics_only_under_its_own_certificate() {
    use vsgraphs_proto::ros::MessageType;
    use vsgraphs_server::config::RosRobotConfig;
    let dir = tempfile::tempdir().unwrap();
    let site = dir.path().join("site");
    let robots = ["ros-cam".to_owned(), "good".to_owned()];
    certificates::make(&site, &["127.0.0.1".into()], &robots).unwrap();
    let endpoint = format!("tls/127.0.0.1:{}", free_port());
    let ros_robot = RosRobotConfig {
        id: "ros-cam".into(),
        colour: "/cam/image_raw".into(),
        depth: "/cam/depth/image_raw".into(),
        camera_info: "/cam/camera_info".into(),
        ..RosRobotConfig::default()
    };
    let colour_key =
        ros_robot
            .key_format()
            .publication(&ros_robot.colour, MessageType::Image, "RIHS01_0");
    let configured = ros_robot.clone();
    let test = TestServer::start_with(|c| {
        c.zenoh.listen = vec![endpoint.clone()];
        c.zenoh.tls = TlsSettings {
            mutual: true,
            ..tls(&site, "ca.pem", Some("server"))
        };
        c.ingest.allowed_robots = robots.to_vec();
        c.ros.robots = vec![configured];
    })
    .await;
    let session = |certificate: &str| {
        let settings = vsgraphs_sdk::zenoh_config::ZenohSettings {
            connect: vec![endpoint.clone()],
            multicast_scouting: false,
            tls: tls(&site, "ca.pem", Some(certificate)),
            ..Default::default()
        };
        async move { zenoh::open(settings.to_config().unwrap()).await.unwrap() }
    };
    let rejected = || async {
        let status = test.client.robot("ros-cam").await.ok()?;
        status.frames.rejected_by_reason.get("ros_message").copied()
    };
    let garbage = b"\x00\x01\x00\x00not an image".to_vec();

    // The ROS robot's router: the server's subscription reaches it, its messages reach ingest.
    let robot = session("robot-ros-cam").await;
    let publisher = robot.declare_publisher(colour_key.clone()).await.unwrap();
    wait_for(
        "the server's subscription",
        Duration::from_secs(20),
        || async {
            publisher
                .matching_status()
                .await
                .unwrap()
                .matching()
                .then_some(())
        },
    )
    .await;
    publisher.put(garbage.clone()).await.unwrap();
    wait_for("the first message", Duration::from_secs(20), || async {
        rejected().await.filter(|&n| n == 1)
    })
    .await;

    // Another robot of the site puts on the ROS robot's key: zenoh refuses it.
    let impostor = session("robot-good").await;
    let _ = impostor.put(colour_key.clone(), garbage.clone()).await;
    publisher.put(garbage.clone()).await.unwrap();
    wait_for("the second message", Duration::from_secs(20), || async {
        rejected().await.filter(|&n| n >= 2)
    })
    .await;
    tokio::time::sleep(Duration::from_millis(500)).await;
    assert_eq!(
        rejected().await,
        Some(2),
        "the impostor's message was refused"
    );
    impostor.close().await.unwrap();
    robot.close().await.unwrap();
    test.server.stop().await.unwrap();
}
