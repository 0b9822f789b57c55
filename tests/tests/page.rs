//! The page in a real browser: a virtual robot walks seq01 (two rooms joined by a door) over
//! real zenoh to the real server while headless Chromium shows the server's page. The page
//! loads with no console error, a keyframe mapped after it loaded shows up without a reload,
//! the rooms, doorway and robot it draws are the API's, clicking a room shows its details, and
//! names with markup in them are shown as text. Screenshots of both views are saved under
//! `target/test-artefacts/page/`.

use serde_json::Value;
use std::collections::BTreeSet;
use std::path::PathBuf;
use std::time::Duration;
use vsgraphs_sdk::player::Rate;
use vsgraphs_sdk::simulated::{self, SimOptions};
use vsgraphs_tests::browser::Browser;
use vsgraphs_tests::*;

const PAGE_WAIT: Duration = Duration::from_secs(30);

fn artefacts() -> PathBuf {
    PathBuf::from(env!("CARGO_MANIFEST_DIR")).join("../target/test-artefacts/page")
}

/// Runs blocking browser work off the test's runtime, handing the browser back.
async fn in_browser<T: Send + 'static>(
    browser: Browser,
    work: impl FnOnce(&mut Browser) -> anyhow::Result<T> + Send + 'static,
) -> (Browser, T) {
    tokio::task::spawn_blocking(move || {
        let mut browser = browser;
        let value = work(&mut browser);
        match value {
            Ok(value) => (browser, value),
            Err(e) => panic!("{e:#}; errors on the page: {:?}", browser.errors),
        }
    })
    .await
    .unwrap()
}

fn as_u64(value: &Value) -> u64 {
    value
        .as_str()
        .and_then(|s| s.parse().ok())
        .or(value.as_u64())
        .unwrap_or(0)
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn the_page_draws_seq01_live_and_shows_what_is_clicked() {
    let site = SimulatedSite::builtin("seq01");
    let test = site.server().await;
    let building = &site.building;
    let renderer = site.renderer.clone();
    let walk = site.walks().remove(0);
    let frames = walk.times.len() as u64;
    let robot = test.robot("sim-1").await;
    let streaming = tokio::spawn(async move {
        let options = SimOptions {
            rate: Rate::Hz(15.0),
            ..SimOptions::default()
        };
        simulated::stream(&robot, renderer, walk, &options, |_, _| {})
            .await
            .unwrap();
        robot
    });

    // The page opens while the robot is still mapping.
    wait_for("the first keyframes", Duration::from_secs(60), || async {
        let maps = test.client.server_maps().await.ok()?;
        maps.first().filter(|m| m.keyframes >= 2).map(|m| m.id)
    })
    .await;
    let url = format!("http://{}/", test.server.http_addr());
    let browser = tokio::task::spawn_blocking(move || Browser::open(&url, 1600, 1000))
        .await
        .unwrap()
        .expect("Chromium starts (Debian's chromium package; $CHROMIUM names another)");
    let (browser, (first, origin)) = in_browser(browser, |b| {
        let first = b.wait_for(
            "the map's keyframes on the page",
            PAGE_WAIT,
            "document.getElementById('map-stats').dataset.keyframes",
        )?;
        let origin = b.eval("performance.timeOrigin")?;
        Ok((as_u64(&first), origin))
    })
    .await;
    // A keyframe mapped after the page loaded shows up in it, with no reload.
    let (browser, later) = in_browser(browser, move |b| {
        let later = b.wait_for(
            "a keyframe more on the page",
            Duration::from_secs(60),
            &format!(
                "(() => {{ const k = Number(document.getElementById('map-stats').dataset.keyframes); \
                 return k > {first} ? k : null; }})()"
            ),
        )?;
        assert_eq!(b.eval("performance.timeOrigin")?, origin, "the page reloaded");
        Ok(as_u64(&later))
    })
    .await;
    eprintln!("keyframes on the page: {first} when it loaded, then {later}");

    // The walk done and its rooms mapped, the page shows what the API says.
    let robot = streaming.await.unwrap();
    wait_for("every frame handled", Duration::from_secs(120), || async {
        let f = test.client.robot("sim-1").await.ok()?.frames;
        (f.processed + f.dropped + f.rejected >= frames).then_some(())
    })
    .await;
    let map_id = test.client.server_maps().await.unwrap()[0].id;
    let (spaces, doorways) = wait_for(
        "both rooms and the doorway",
        Duration::from_secs(30),
        || async {
            let spaces = test.client.spaces(map_id).await.ok()?;
            let doorways = test.client.doorways(map_id).await.ok()?;
            (spaces.len() == 2 && doorways.len() == 1).then_some((spaces, doorways))
        },
    )
    .await;
    let summary = test.client.server_maps().await.unwrap()[0].clone();
    let status = test.client.robot("sim-1").await.unwrap();
    let tracking = status.tracking.expect("tracked");
    assert_eq!(tracking.map_id, Some(map_id));

    let space_names: BTreeSet<String> = spaces
        .iter()
        .map(|s| format!("{} · room", s.name))
        .collect();
    let door = doorways[0].clone();
    let room = spaces[0].clone();
    let api_keyframes = summary.keyframes;
    let (browser, ()) = in_browser(browser, move |b| {
        // The lists.
        let listed = b.wait_for(
            "the rooms listed",
            PAGE_WAIT,
            "(() => { const l = [...document.querySelectorAll('#spaces li')].map((li) => li.textContent); \
             return l.length === 2 ? l : null; })()",
        )?;
        let listed: BTreeSet<String> = listed
            .as_array()
            .unwrap()
            .iter()
            .map(|v| v.as_str().unwrap().to_owned())
            .collect();
        assert_eq!(listed, space_names);
        let doors = b.eval(
            "[...document.querySelectorAll('#doorways li')].map((li) => li.dataset.doorwayId)",
        )?;
        assert_eq!(doors, serde_json::json!([door.id.to_string()]));
        // The counts as the API has them once the robot stopped.
        b.wait_for(
            "the page's keyframe count to reach the API's",
            PAGE_WAIT,
            &format!(
                "document.getElementById('map-stats').dataset.keyframes === '{api_keyframes}'"
            ),
        )?;
        // What the top view drew: both rooms with their outlines, the doorway, the robot.
        let drawn = b.wait_for(
            "the rooms, doorway and robot drawn",
            PAGE_WAIT,
            "(() => { const d = JSON.parse(document.getElementById('top').dataset.drawn || 'null'); \
             return d && d.spaces.length === 2 && d.doorways.length === 1 && d.robots.length === 1 ? d : null; })()",
        )?;
        let drawn_spaces: BTreeSet<u64> = drawn["spaces"]
            .as_array()
            .unwrap()
            .iter()
            .map(|s| s["id"].as_u64().unwrap())
            .collect();
        assert_eq!(
            drawn_spaces,
            spaces.iter().map(|s| u64::from(s.id)).collect()
        );
        assert!(drawn["spaces"]
            .as_array()
            .unwrap()
            .iter()
            .all(|s| s["outline"] == true));
        assert_eq!(drawn["doorways"][0]["id"], door.id);
        assert_eq!(drawn["robots"][0]["id"], "sim-1");
        // Its path: the walk goes round both rooms, metres long, in positions 5 cm apart.
        assert_eq!(drawn["paths"][0]["robot"], "sim-1");
        let positions = drawn["paths"][0]["positions"].as_u64().unwrap();
        assert!(positions > 100, "{drawn}");

        // Clicking the room's centre on the canvas shows its details.
        let at = drawn["spaces"]
            .as_array()
            .unwrap()
            .iter()
            .find(|s| s["id"] == room.id)
            .unwrap()["at"]
            .clone();
        let origin = b.eval(
            "(() => { const r = document.getElementById('top').getBoundingClientRect(); return [r.left, r.top]; })()",
        )?;
        let x = origin[0].as_f64().unwrap() + at[0].as_f64().unwrap();
        let y = origin[1].as_f64().unwrap() + at[1].as_f64().unwrap();
        for kind in ["mousePressed", "mouseReleased"] {
            b.call(
                "Input.dispatchMouseEvent",
                serde_json::json!({ "type": kind, "x": x, "y": y, "button": "left", "clickCount": 1 }),
            )?;
        }
        b.wait_for(
            "the room's details",
            PAGE_WAIT,
            &format!(
                "document.getElementById('details-title').textContent === {}",
                serde_json::json!(room.name)
            ),
        )?;
        let details = b
            .eval("document.getElementById('details-body').textContent")?
            .as_str()
            .unwrap()
            .to_owned();
        for wall in &room.walls {
            assert!(details.contains(&format!("wall {wall}")), "{details}");
        }
        let door_name = door.name.clone().unwrap();
        assert!(details.contains(&door_name), "{details}");
        assert!(details.contains("m²"), "{details}");
        b.screenshot(&artefacts().join("top-view.png"))?;

        // The doorway from the list: the two rooms it joins.
        b.eval("document.querySelector('#doorways li').click()")?;
        let details = b.wait_for(
            "the doorway's details",
            PAGE_WAIT,
            &format!(
                "document.getElementById('details-title').textContent === {} && \
                 document.getElementById('details-body').textContent",
                serde_json::json!(door_name)
            ),
        )?;
        for name in &door.between {
            assert!(details.as_str().unwrap().contains(name.as_str()), "{details}");
        }

        // The graph view draws with WebGL.
        b.eval("document.getElementById('tab-graph').click()")?;
        b.wait_for(
            "the graph view's canvas",
            PAGE_WAIT,
            "document.querySelector('#graph-view canvas') !== null",
        )?;
        std::thread::sleep(Duration::from_millis(1500));
        b.screenshot(&artefacts().join("graph-view.png"))?;
        b.eval("document.getElementById('tab-top').click()")?;
        Ok(())
    })
    .await;

    // Names with markup are text, never markup.
    let hostile = r#"<img src=x onerror="window.pwned=1">Tom's "room""#;
    let mut renamed = building.dictionary_v1();
    renamed["rooms"][0]["name"] = hostile.into();
    test.client
        .set_dictionary(&renamed.to_string())
        .await
        .unwrap();
    let (browser, ()) = in_browser(browser, move |b| {
        b.wait_for(
            "the hostile name listed",
            PAGE_WAIT,
            &format!(
                "[...document.querySelectorAll('#spaces li')].some((li) => li.textContent.startsWith({}))",
                serde_json::json!(hostile)
            ),
        )?;
        assert_eq!(b.eval("document.querySelectorAll('img').length")?, 0);
        assert_eq!(b.eval("window.pwned === undefined")?, true);
        Ok(())
    })
    .await;
    assert!(
        browser.errors.is_empty(),
        "errors on the page: {:?}",
        browser.errors
    );
    drop(browser);
    robot.close().await.unwrap();
}
