//! Measures the page against a running server, in headless Chromium: how long until its first
//! draw of a map, the main-thread time each live update takes in the top view and in the graph
//! view, and the bytes per second its event stream carries.
//!
//! ```text
//! cargo run --release -p vsgraphs-tests --example page_bench -- http://127.0.0.1:8080/ [SECONDS] [SCREENSHOTS_DIR]
//! ```
//!
//! With a folder, it also leaves a screenshot of each view there (`top.png`, `graph.png`).
//!
//! Run it while robots stream, so there are updates to measure (BENCHMARKS.md, "The page").

use anyhow::Context;
use serde_json::Value;
use std::io::{Read, Write};
use std::net::TcpStream;
use std::time::{Duration, Instant};
use vsgraphs_tests::browser::Browser;

fn main() -> anyhow::Result<()> {
    let mut args = std::env::args().skip(1);
    let url = args
        .next()
        .unwrap_or_else(|| "http://127.0.0.1:8080/".into());
    let seconds: u64 = args.next().map(|s| s.parse()).transpose()?.unwrap_or(30);
    let screenshots = args.next().map(std::path::PathBuf::from);
    let address = url
        .trim_start_matches("http://")
        .trim_end_matches('/')
        .to_owned();

    // The event stream as a page gets it, counted beside the browser.
    let counting =
        std::thread::spawn(move || stream_bytes(&address, Duration::from_secs(seconds * 2)));

    let mut browser = Browser::open(&url, 1600, 1000)?;
    let first = browser.wait_for(
        "the first draw of a map",
        Duration::from_secs(60),
        "document.body.dataset.firstMapDraw",
    )?;
    let stats = browser.eval("document.getElementById('map-stats').textContent")?;
    println!("map: {}", stats.as_str().unwrap_or("?"));
    println!(
        "first draw of the map: {:.0} ms after navigation started",
        as_f64(&first)
    );
    let timing = browser.eval("JSON.stringify(window.pageTiming)")?;
    println!("by then: {}", timing.as_str().unwrap_or("?"));

    // How long a change takes to reach the page: the map's keyframe count as the API has it
    // (asked every 10 ms on a thread) against the count the page shows (asked as often).
    let delays = change_delays(&mut browser, &url, 8)?;
    if !delays.is_empty() {
        let mut sorted = delays.clone();
        sorted.sort_by(f64::total_cmp);
        println!(
            "a new keyframe on the page after the API has it: median {:.0} ms, max {:.0} ms \
             ({} keyframes)",
            sorted[sorted.len() / 2],
            sorted[sorted.len() - 1],
            sorted.len()
        );
    }

    for view in ["top", "graph"] {
        browser.eval(&format!("document.getElementById('tab-{view}').click()"))?;
        std::thread::sleep(Duration::from_secs(2));
        // The longest draw of this view alone, its first (whole) draw left out.
        browser.eval("window.pageTiming.renderMsMax = 0")?;
        let before = sample(&mut browser)?;
        std::thread::sleep(Duration::from_secs(seconds));
        let after = sample(&mut browser)?;
        let renders = after.renders - before.renders;
        let events = after.events - before.events;
        println!(
            "{view} view, {seconds} s: {events} events handled in {:.1} ms ({:.2} ms each); \
             {renders} draws, {:.1} ms each on average, {:.1} ms the longest; main thread \
             busy {:.1} % ({:.0} ms of tasks)",
            after.event_ms - before.event_ms,
            (after.event_ms - before.event_ms) / events.max(1) as f64,
            (after.render_ms - before.render_ms) / renders.max(1) as f64,
            after.render_ms_max,
            100.0 * (after.task_s - before.task_s) / seconds as f64,
            1e3 * (after.task_s - before.task_s),
        );
        if let Some(dir) = &screenshots {
            browser.screenshot(&dir.join(format!("{view}.png")))?;
        }
    }
    let (first, rest, elapsed) = counting.join().expect("the counting thread")?;
    let steady = elapsed.as_secs_f64() - FIRST.as_secs_f64();
    println!(
        "event stream: {first} bytes in its first {} s (the whole map), then {rest} bytes in \
         {steady:.1} s: {:.1} kB/s",
        FIRST.as_secs(),
        rest as f64 / steady / 1e3
    );
    anyhow::ensure!(
        browser.errors.is_empty(),
        "errors on the page: {:?}",
        browser.errors
    );
    Ok(())
}

/// For `count` new keyframes of the page's map: milliseconds from the API's first answer with
/// the new count to the page's showing it.
fn change_delays(browser: &mut Browser, url: &str, count: usize) -> anyhow::Result<Vec<f64>> {
    let map_id = browser
        .eval("document.getElementById('map-stats').dataset.mapId")?
        .as_str()
        .context("no map on the page")?
        .to_owned();
    let address = url
        .trim_start_matches("http://")
        .trim_end_matches('/')
        .to_owned();
    let start = Instant::now();
    let (tx, rx) = std::sync::mpsc::channel::<(u64, f64)>();
    let done = std::sync::Arc::new(std::sync::atomic::AtomicBool::new(false));
    let stop = done.clone();
    let watching = std::thread::spawn(move || -> anyhow::Result<()> {
        let mut last = 0;
        while start.elapsed() < Duration::from_secs(120)
            && !stop.load(std::sync::atomic::Ordering::Relaxed)
        {
            let body = http_body(&address, &format!("/api/v1/maps/{map_id}?max_points=0"))?;
            let view: Value = serde_json::from_str(&body)?;
            let keyframes = view["keyframe_count"].as_u64().unwrap_or(0);
            if keyframes != last {
                last = keyframes;
                if tx
                    .send((keyframes, start.elapsed().as_secs_f64() * 1e3))
                    .is_err()
                {
                    return Ok(());
                }
            }
            std::thread::sleep(Duration::from_millis(10));
        }
        Ok(())
    });
    let mut api_at = std::collections::HashMap::new();
    let mut delays = Vec::new();
    let mut shown = 0;
    while delays.len() < count && start.elapsed() < Duration::from_secs(120) {
        while let Ok((keyframes, at)) = rx.try_recv() {
            api_at.entry(keyframes).or_insert(at);
        }
        let on_page =
            as_f64(&browser.eval("document.getElementById('map-stats').dataset.keyframes")?) as u64;
        if on_page != shown {
            let now = start.elapsed().as_secs_f64() * 1e3;
            // The first count seen is the one the page already had.
            if shown != 0 {
                if let Some(at) = api_at.get(&on_page) {
                    delays.push(now - at);
                }
            }
            shown = on_page;
        }
        std::thread::sleep(Duration::from_millis(10));
    }
    done.store(true, std::sync::atomic::Ordering::Relaxed);
    drop(rx);
    watching.join().expect("the watching thread")?;
    Ok(delays)
}

/// The body of a plain HTTP GET (the server answers with a length).
fn http_body(address: &str, path: &str) -> anyhow::Result<String> {
    let mut stream = TcpStream::connect(address)?;
    write!(
        stream,
        "GET {path} HTTP/1.1\r\nHost: {address}\r\nConnection: close\r\n\r\n"
    )?;
    let mut response = String::new();
    stream.read_to_string(&mut response)?;
    let (_, body) = response.split_once("\r\n\r\n").context("no body")?;
    Ok(body.to_owned())
}

fn as_f64(value: &Value) -> f64 {
    value
        .as_str()
        .and_then(|s| s.parse().ok())
        .or(value.as_f64())
        .unwrap_or(f64::NAN)
}

struct Sample {
    events: u64,
    event_ms: f64,
    renders: u64,
    render_ms: f64,
    render_ms_max: f64,
    task_s: f64,
}

fn sample(browser: &mut Browser) -> anyhow::Result<Sample> {
    let timing: Value = serde_json::from_str(
        browser
            .eval("JSON.stringify(window.pageTiming)")?
            .as_str()
            .context("no pageTiming")?,
    )?;
    let metrics = browser.metrics()?;
    Ok(Sample {
        events: timing["events"].as_u64().unwrap_or(0),
        event_ms: timing["eventMs"].as_f64().unwrap_or(0.0),
        renders: timing["renders"].as_u64().unwrap_or(0),
        render_ms: timing["renderMs"].as_f64().unwrap_or(0.0),
        render_ms_max: timing["renderMsMax"].as_f64().unwrap_or(0.0),
        task_s: metrics.get("TaskDuration").copied().unwrap_or(0.0),
    })
}

/// The part of the event stream counted apart: it carries the whole map.
const FIRST: Duration = Duration::from_secs(5);

/// Reads `/api/v1/events` for `how_long` and counts the bytes of its body: those of its first
/// [`FIRST`] seconds, those after, and how long it read.
fn stream_bytes(address: &str, how_long: Duration) -> anyhow::Result<(u64, u64, Duration)> {
    let mut stream = TcpStream::connect(address)?;
    write!(
        stream,
        "GET /api/v1/events HTTP/1.1\r\nHost: {address}\r\nAccept: text/event-stream\r\n\r\n"
    )?;
    stream.set_read_timeout(Some(Duration::from_millis(200)))?;
    let start = Instant::now();
    let (mut first, mut rest) = (0u64, 0u64);
    let mut head = true;
    let mut buffer = [0u8; 65536];
    while start.elapsed() < how_long {
        match stream.read(&mut buffer) {
            Ok(0) => break,
            Ok(n) => {
                let mut body = &buffer[..n];
                if head {
                    if let Some(end) = body.windows(4).position(|w| w == b"\r\n\r\n") {
                        body = &body[end + 4..];
                        head = false;
                    }
                }
                if !head && start.elapsed() < FIRST {
                    first += body.len() as u64;
                } else if !head {
                    rest += body.len() as u64;
                }
            }
            Err(e)
                if matches!(
                    e.kind(),
                    std::io::ErrorKind::WouldBlock | std::io::ErrorKind::TimedOut
                ) => {}
            Err(e) => return Err(e.into()),
        }
    }
    Ok((first, rest, start.elapsed()))
}
