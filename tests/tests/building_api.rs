//! A virtual robot walks seq01 (two rooms joined by a door) and streams it live over real zenoh
//! to the real server, with the building's semantic dictionary. The HTTP API then lists the
//! map with its robot, the two rooms as neighbours, the doorway between them, the route from one
//! to the other, the map's Situational Graph, and the room the robot is in at the end of its walk;
//! a dictionary replaced through the API renames the rooms without restarting the robot.

use std::collections::{BTreeMap, BTreeSet};
use std::time::Duration;
use vsgraphs_proto::api::{GraphLayer, SceneGraph, SpaceKind};
use vsgraphs_sdk::player::Rate;
use vsgraphs_sdk::simulated::{self, SimOptions};
use vsgraphs_sdk::{ClientError, Delivery, Robot, RobotConfig};
use vsgraphs_tests::*;

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn the_api_answers_rooms_doorways_route_and_where_the_robot_is_after_seq01() {
    let site = SimulatedSite::builtin("seq01");
    let test = site.server().await;
    let (scenario, building) = (&site.scenario, &site.building);
    let renderer = site.renderer.clone();
    let walk = site.walks().remove(0);
    let frames = walk.times.len();

    let mut config = RobotConfig::connecting_to("sim-1", &test.zenoh_endpoint);
    config.delivery = Delivery::Reliable;
    let robot = Robot::connect(config).await.unwrap();
    let options = SimOptions {
        // Half the walk's pace: what the server keeps up with in this build.
        rate: Rate::Hz(15.0),
        ..SimOptions::default()
    };
    let summary = simulated::stream(&robot, renderer.clone(), walk.clone(), &options, |_, _| {})
        .await
        .unwrap();
    assert_eq!(summary.frames_sent, frames as u64);
    let status = wait_for(
        "every frame processed",
        Duration::from_secs(120),
        || async {
            let status = test.client.robot("sim-1").await.ok()?;
            let f = &status.frames;
            (f.processed + f.dropped + f.rejected >= frames as u64).then_some(status)
        },
    )
    .await;
    let tracking = status.tracking.clone().expect("tracking is on by default");
    // Frames the server could not keep pace with are dropped by design (a live robot wants its
    // newest frames); how many depends on the machine's load, so the check is on those tracked.
    let processed = tracking.frames_tracked + tracking.frames_untracked;
    eprintln!(
        "{processed} of {frames} frames processed, {} dropped",
        status.frames.dropped
    );
    assert!(
        tracking.frames_tracked as f64 >= 0.95 * processed as f64 && processed > 0,
        "{tracking:?}"
    );

    // One map on the server, mapped by this robot; its semantic layer lands a little after the
    // last keyframe: wait for both rooms and the doorway.
    let maps = test.client.server_maps().await.unwrap();
    assert_eq!(maps.len(), 1, "{maps:?}");
    assert_eq!(maps[0].robots, vec!["sim-1".to_string()]);
    let map_id = maps[0].id;
    assert_eq!(tracking.map_id, Some(map_id));
    let spaces = wait_for(
        "both rooms and the doorway",
        Duration::from_secs(30),
        || async {
            let spaces = test.client.spaces(map_id).await.ok()?;
            let doorways = test.client.doorways(map_id).await.ok()?;
            (spaces.len() == 2 && doorways.len() == 1).then_some(spaces)
        },
    )
    .await;
    let names: BTreeSet<&str> = spaces.iter().map(|s| s.name.as_str()).collect();
    let truth: BTreeSet<&str> = building.spaces.iter().map(|s| s.name.as_str()).collect();
    assert_eq!(names, truth);
    assert!(spaces
        .iter()
        .all(|s| s.kind == SpaceKind::Room && s.walls.len() == 4));
    let (a, b) = (&spaces[0], &spaces[1]);
    assert_eq!(
        (a.neighbours.clone(), b.neighbours.clone()),
        (vec![b.id], vec![a.id])
    );

    // The doorway joins them, named as the dictionary names the door, and sits where the door
    // is: its distances to the two rooms' centres are the building's (the map has its own frame).
    let doorways = test.client.doorways(map_id).await.unwrap();
    let doorway = &doorways[0];
    let door = &building.doorways[0];
    assert_eq!(doorway.name.as_deref(), Some(door.name.as_str()));
    let between: BTreeSet<&str> = doorway.between.iter().map(|s| s.as_str()).collect();
    assert_eq!(between, truth);
    assert_eq!(a.doorways, vec![doorway.id]);
    let at = nalgebra::Vector3::from(doorway.world_from_doorway.translation_m);
    let true_at = door.world_from_doorway.translation.vector;
    for space in &spaces {
        let true_space = building
            .spaces
            .iter()
            .find(|s| s.name == space.name)
            .unwrap();
        let mapped = (at - nalgebra::Vector3::from(space.centre)).norm();
        let actual = (true_at - nalgebra::Vector3::from(true_space.centre)).norm();
        assert!(
            (mapped - actual).abs() < 0.1,
            "{}: {mapped} m from the doorway, {actual} m in the building",
            space.name
        );
    }
    assert!((doorway.width_m - 0.9).abs() < 0.15, "{doorway:?}");

    // The route from one room to the other goes through that doorway; by name or by id.
    let route = test.client.route(map_id, &a.name, &b.name).await.unwrap();
    let passed: Vec<&str> = route.spaces.iter().map(|s| s.name.as_str()).collect();
    assert_eq!(passed, vec![a.name.as_str(), b.name.as_str()]);
    assert_eq!(route.doorways, vec![doorway.id]);
    assert!(route.length_m > 1.0 && route.length_m < 20.0, "{route:?}");
    let by_id = test
        .client
        .route(map_id, &b.id.to_string(), &a.id.to_string())
        .await
        .unwrap();
    assert_eq!(by_id.doorways, vec![doorway.id]);
    match test.client.route(map_id, &a.name, "Nowhere").await {
        Err(ClientError::Api { status, body, .. }) => {
            assert_eq!((status, body.error.as_str()), (404, "space_not_found"));
            assert!(body.message.contains("Nowhere"), "{}", body.message);
        }
        other => panic!("a route to an unknown room: {other:?}"),
    }
    let one = test.client.space(map_id, &a.name).await.unwrap();
    assert_eq!(one, *a);

    // The room the robot ends its walk in, as the building has it.
    let end = walk.world_from_camera.last().unwrap().translation.vector;
    let ends_in = scenario
        .plan
        .spaces
        .iter()
        .find(|s| (0..2).all(|i| s.min[i] < end[i] && end[i] < s.max[i]))
        .unwrap();
    let status = test.client.robot("sim-1").await.unwrap();
    let space = status.tracking.and_then(|t| t.space);
    assert_eq!(
        space.as_ref().map(|s| s.name.as_str()),
        Some(ends_in.name.as_str())
    );

    // The Situational Graph: three layers, markers on walls and walls of rooms.
    let graph = test.client.graph(map_id).await.unwrap();
    for layer in [
        GraphLayer::Keyframes,
        GraphLayer::Structure,
        GraphLayer::Spaces,
    ] {
        assert!(graph.nodes.iter().any(|n| n.layer == layer), "{layer:?}");
    }
    let ids: BTreeSet<&str> = graph.nodes.iter().map(|n| n.id.as_str()).collect();
    assert!(graph
        .edges
        .iter()
        .all(|e| ids.contains(e.from.as_str()) && ids.contains(e.to.as_str())));
    for s in &spaces {
        let node = format!("room/{}", s.id);
        let walls = graph
            .edges
            .iter()
            .filter(|e| e.to == node && e.from.starts_with("wall/"));
        assert_eq!(walls.count(), 4, "{node}");
    }

    exports_match_the_api(&test, map_id, &graph).await;

    // A dictionary replaced at run time renames the rooms without a frame more.
    let mut renamed = building.dictionary_v1();
    renamed["rooms"][0]["name"] = "Kitchen".into();
    test.client
        .set_dictionary(&renamed.to_string())
        .await
        .unwrap();
    let kitchen = building.spaces[0].name.clone();
    let spaces = wait_for("the rooms renamed", Duration::from_secs(10), || async {
        let spaces = test.client.spaces(map_id).await.ok()?;
        spaces.iter().any(|s| s.name == "Kitchen").then_some(spaces)
    })
    .await;
    assert!(spaces.iter().all(|s| s.name != kitchen), "{spaces:?}");
    assert_eq!(spaces.len(), 2);

    let names: Vec<String> = spaces.iter().map(|s| s.name.clone()).collect();
    hostile_requests(
        &format!("http://{}", test.server.http_addr()),
        map_id,
        &names,
    )
    .await;
    robot.close().await.unwrap();
}

/// Requests to every route the API reads from, with path segments and query parameters as a
/// client could get them wrong or craft them: known and unknown robots, maps and spaces, ids
/// beyond 32 bits or negative, encoded slashes and nulls, parameters of the wrong type, at
/// extremes, repeated or unknown. The server answers each without a server error, in JSON where
/// it answers with a document, and goes on serving.
async fn hostile_requests(base: &str, map_id: u32, spaces: &[String]) {
    use proptest::prelude::*;
    use proptest::strategy::ValueTree;

    let mut known: Vec<String> = vec!["sim-1".into(), map_id.to_string()];
    known.extend(spaces.iter().cloned());
    let segment = prop_oneof![
        4 => prop::sample::select(known),
        1 => prop::sample::select(vec![
            "0", "-1", "4294967296", "18446744073709551616", "%00", "..", "a/b", "%2F", " ", "",
        ])
        .prop_map(str::to_owned),
        1 => "[ -~]{0,12}",
        1 => any::<u32>().prop_map(|n| n.to_string()),
    ];
    let routes = prop::sample::select(vec![
        "robots/*",
        "robots/*/detections",
        "robots/*/trajectory",
        "robots/*/maps",
        "robots/*/maps/*",
        "robots/*/maps/*/model",
        "maps/*",
        "maps/*/file",
        "maps/*/model",
        "maps/*/trajectories",
        "maps/*/spaces",
        "maps/*/spaces/*",
        "maps/*/doorways",
        "maps/*/walls",
        "maps/*/route",
        "maps/*/graph",
        "maps",
        "merges",
        "robots",
        "dictionary",
        "*",
        "*/*/*",
    ]);
    let value = prop_oneof![
        prop::sample::select(vec![
            "json",
            "tum",
            "room",
            "corridor",
            "0",
            "1",
            "-1",
            "4294967296",
            "18446744073709551616",
            "1e9",
            "NaN",
            "",
            "%ZZ",
            "true",
        ])
        .prop_map(str::to_owned),
        prop::sample::select(spaces.to_vec()),
        "[ -~]{0,10}",
    ];
    let parameter = (
        prop::sample::select(vec![
            "format",
            "map",
            "max_points",
            "kind",
            "from",
            "to",
            "offset",
            "limit",
            "x",
        ]),
        value,
    );
    let request = (
        routes,
        prop::collection::vec(segment, 3),
        prop::collection::vec(parameter, 0..4),
    );
    let http = reqwest::Client::new();
    let mut runner = proptest::test_runner::TestRunner::deterministic();
    let mut statuses = std::collections::BTreeMap::new();
    for _ in 0..400 {
        let (route, segments, parameters) = request.new_tree(&mut runner).unwrap().current();
        let mut url = reqwest::Url::parse(&format!("{base}/api/v1/")).unwrap();
        {
            let mut path = url.path_segments_mut().unwrap();
            path.pop_if_empty();
            let mut given = segments.iter();
            for part in route.split('/') {
                path.push(if part == "*" {
                    given.next().unwrap()
                } else {
                    part
                });
            }
        }
        if !parameters.is_empty() {
            let mut query = url.query_pairs_mut();
            for (key, value) in &parameters {
                query.append_pair(key, value);
            }
        }
        let response = http.get(url.clone()).send().await.unwrap();
        let status = response.status();
        let json = response
            .headers()
            .get("content-type")
            .is_some_and(|t| t.as_bytes().starts_with(b"application/json"));
        let body = response.bytes().await.unwrap();
        assert!(!status.is_server_error(), "{url}: {status} {body:?}");
        if json {
            serde_json::from_slice::<serde_json::Value>(&body)
                .unwrap_or_else(|e| panic!("{url}: not JSON ({e})"));
        }
        if status.is_client_error() {
            let error: serde_json::Value = serde_json::from_slice(&body)
                .unwrap_or_else(|_| panic!("{url}: {status} without a JSON error: {body:?}"));
            assert!(error["error"].is_string(), "{url}: {error}");
        }
        *statuses.entry(status.as_u16()).or_insert(0) += 1;
    }
    eprintln!("hostile requests by status: {statuses:?}");
    let health = http
        .get(format!("{base}/api/v1/health"))
        .send()
        .await
        .unwrap();
    assert!(health.status().is_success());
}

/// The map's GraphML, read by an XML parser, holds the JSON graph's nodes with their layers,
/// kinds, names and positions, and its edges; its PLY holds every point the map counts.
async fn exports_match_the_api(test: &TestServer, map_id: u32, graph: &SceneGraph) {
    use quick_xml::events::Event;
    let base = format!("http://{}/api/v1/maps/{map_id}", test.server.http_addr());
    let response = reqwest::get(format!("{base}/graph?format=graphml"))
        .await
        .unwrap();
    assert_eq!(response.status(), 200);
    assert_eq!(
        response.headers()["content-type"],
        "application/graphml+xml"
    );
    let xml = response.text().await.unwrap();
    let mut reader = quick_xml::Reader::from_str(&xml);
    // (node id, key → value) and (source, target), as the file says.
    let mut nodes: Vec<(String, BTreeMap<String, String>)> = Vec::new();
    let mut edges: Vec<(String, String)> = Vec::new();
    let mut key: Option<(String, String)> = None;
    let v1 = quick_xml::XmlVersion::Implicit1_0;
    loop {
        match reader.read_event().expect("well-formed XML") {
            Event::Start(e) | Event::Empty(e) => {
                let attribute = |name: &str| {
                    e.try_get_attribute(name)
                        .unwrap()
                        .map(|a| a.normalized_value(v1).unwrap().into_owned())
                };
                match e.name().as_ref() {
                    "node" => nodes.push((attribute("id").unwrap(), BTreeMap::new())),
                    "edge" => {
                        edges.push((attribute("source").unwrap(), attribute("target").unwrap()))
                    }
                    "data" => key = attribute("key").map(|k| (k, String::new())),
                    _ => {}
                }
            }
            Event::Text(t) => {
                if let Some((_, text)) = &mut key {
                    text.push_str(&t.xml_content(v1));
                }
            }
            Event::GeneralRef(r) => {
                if let Some((_, text)) = &mut key {
                    let entity = r.xml_content(v1);
                    let resolved = quick_xml::escape::resolve_predefined_entity(&entity);
                    text.push_str(resolved.expect("only XML's own entities"));
                }
            }
            Event::End(e) if e.name().as_ref() == "data" => {
                if let (Some((k, text)), Some((_, data))) = (key.take(), nodes.last_mut()) {
                    data.insert(k, text);
                }
            }
            Event::Eof => break,
            _ => {}
        }
    }
    assert_eq!(nodes.len(), graph.nodes.len());
    for ((id, data), node) in nodes.iter().zip(&graph.nodes) {
        assert_eq!(id, &node.id);
        let layer = serde_json::to_value(node.layer).unwrap();
        assert_eq!(data["layer"], layer.as_str().unwrap(), "{id}");
        assert_eq!(data["kind"], node.kind, "{id}");
        assert_eq!(data.get("name"), node.name.as_ref(), "{id}");
        for (axis, value) in ["x", "y", "z"].iter().zip(node.position) {
            // serde_json reads floats to within an ulp, not always exactly.
            let written: f64 = data[*axis].parse().unwrap();
            assert!(
                (written - value).abs() <= 1e-12,
                "{id} {axis}: {written} vs {value}"
            );
        }
    }
    let expected: Vec<(String, String)> = graph
        .edges
        .iter()
        .map(|e| (e.from.clone(), e.to.clone()))
        .collect();
    assert_eq!(edges, expected);

    let ply = reqwest::get(format!("{base}/points.ply")).await.unwrap();
    assert_eq!(ply.status(), 200);
    let ply = ply.bytes().await.unwrap();
    let end = b"end_header\n";
    let body_at = ply.windows(end.len()).position(|w| w == end).unwrap() + end.len();
    let header = std::str::from_utf8(&ply[..body_at]).unwrap();
    assert!(
        header.starts_with("ply\nformat binary_little_endian 1.0\n"),
        "{header}"
    );
    let vertices: usize = header
        .lines()
        .find_map(|l| l.strip_prefix("element vertex "))
        .unwrap()
        .parse()
        .unwrap();
    let summary = test.client.server_maps().await.unwrap();
    let points = summary.iter().find(|m| m.id == map_id).unwrap().points as usize;
    // Every point the map counts (mapping may still cull a few as its last keyframes settle).
    assert!(
        vertices > 0 && vertices.abs_diff(points) as f64 <= 0.02 * points as f64,
        "{vertices} vs {points}"
    );
    assert_eq!(ply.len() - body_at, vertices * 12);
    let floats: Vec<f32> = ply[body_at..]
        .chunks_exact(4)
        .map(|b| f32::from_le_bytes(b.try_into().unwrap()))
        .collect();
    assert!(floats.iter().all(|x| x.is_finite() && x.abs() < 100.0));
    eprintln!(
        "exports: GraphML {} bytes ({} nodes), PLY {} points",
        xml.len(),
        nodes.len(),
        vertices
    );
}
