//! A real Chromium, headless, driven over the DevTools protocol (JSON over a WebSocket): open
//! a page, evaluate script in it, wait for what it shows, take screenshots, read performance
//! metrics, and collect every console error and uncaught exception the page raised.
//!
//! Blocking: call it from `spawn_blocking` in async tests.

use anyhow::{bail, Context};
use serde_json::{json, Value};
use std::io::{Read, Write};
use std::net::TcpStream;
use std::path::{Path, PathBuf};
use std::process::{Child, Command, Stdio};
use std::time::{Duration, Instant};
use tungstenite::stream::MaybeTlsStream;
use tungstenite::{Message, WebSocket};

/// The browser to run: `$CHROMIUM`, else Debian's `chromium`.
pub fn chromium_binary() -> PathBuf {
    std::env::var_os("CHROMIUM")
        .map(PathBuf::from)
        .unwrap_or_else(|| PathBuf::from("chromium"))
}

pub struct Browser {
    child: Child,
    socket: WebSocket<MaybeTlsStream<TcpStream>>,
    next_id: u64,
    /// Console errors and uncaught exceptions, as the page raised them.
    pub errors: Vec<String>,
    _profile: tempfile::TempDir,
}

impl Browser {
    /// Starts Chromium on `url` in a window of `width`×`height` CSS pixels.
    pub fn open(url: &str, width: u32, height: u32) -> anyhow::Result<Self> {
        let profile = tempfile::tempdir()?;
        let child = Command::new(chromium_binary())
            .args([
                "--headless=new",
                // Root in CI containers: Chromium's sandbox needs user namespaces it may lack.
                "--no-sandbox",
                "--remote-debugging-port=0",
                "--no-first-run",
                "--no-default-browser-check",
                "--disable-extensions",
                // WebGL (the graph view) on the CPU: CI machines have no GPU.
                "--use-angle=swiftshader",
                "--enable-unsafe-swiftshader",
                &format!("--window-size={width},{height}"),
                &format!("--user-data-dir={}", profile.path().display()),
                "about:blank",
            ])
            .stdout(Stdio::null())
            .stderr(Stdio::null())
            .spawn()
            .with_context(|| format!("starting {}", chromium_binary().display()))?;
        let port = devtools_port(profile.path(), Duration::from_secs(30))?;
        // The file can come before the page is listed: ask again for a while.
        let start = Instant::now();
        let page = loop {
            let listed = http_get(port, "/json/list").and_then(|body| {
                let targets: Value = serde_json::from_str(&body)?;
                targets
                    .as_array()
                    .and_then(|t| t.iter().find(|t| t["type"] == "page"))
                    .and_then(|t| t["webSocketDebuggerUrl"].as_str())
                    .map(str::to_owned)
                    .context("Chromium lists no page")
            });
            match listed {
                Ok(page) => break page,
                Err(e) if start.elapsed() > Duration::from_secs(30) => return Err(e),
                Err(_) => std::thread::sleep(Duration::from_millis(100)),
            }
        };
        let (socket, _) = tungstenite::connect(page.as_str())?;
        let mut browser = Self {
            child,
            socket,
            next_id: 0,
            errors: Vec::new(),
            _profile: profile,
        };
        browser.call("Runtime.enable", json!({}))?;
        browser.call("Log.enable", json!({}))?;
        browser.call("Page.enable", json!({}))?;
        browser.call("Performance.enable", json!({}))?;
        browser.call("Page.navigate", json!({ "url": url }))?;
        browser.wait_for(
            "the page to load",
            Duration::from_secs(30),
            &format!(
                "location.href === {} && document.readyState === 'complete'",
                json!(url)
            ),
        )?;
        Ok(browser)
    }

    /// Calls a DevTools method and returns its result; events that arrive meanwhile are read
    /// for errors.
    pub fn call(&mut self, method: &str, params: Value) -> anyhow::Result<Value> {
        self.next_id += 1;
        let id = self.next_id;
        let request = json!({ "id": id, "method": method, "params": params });
        self.socket.send(Message::text(request.to_string()))?;
        loop {
            let message = self.socket.read()?;
            let Ok(text) = message.to_text() else {
                continue;
            };
            let value: Value = serde_json::from_str(text)?;
            if value["id"] == id {
                if let Some(error) = value.get("error") {
                    bail!("{method}: {error}");
                }
                return Ok(value["result"].clone());
            }
            self.note(&value);
        }
    }

    fn note(&mut self, event: &Value) {
        let params = &event["params"];
        match event["method"].as_str() {
            Some("Runtime.exceptionThrown") => self.errors.push(format!(
                "exception: {}",
                params["exceptionDetails"]["exception"]["description"]
                    .as_str()
                    .or(params["exceptionDetails"]["text"].as_str())
                    .unwrap_or("?")
            )),
            Some("Runtime.consoleAPICalled") if params["type"] == "error" => self
                .errors
                .push(format!("console.error: {}", params["args"])),
            Some("Log.entryAdded") if params["entry"]["level"] == "error" => {
                self.errors.push(format!(
                    "log: {} ({})",
                    params["entry"]["text"].as_str().unwrap_or("?"),
                    params["entry"]["url"].as_str().unwrap_or("")
                ))
            }
            _ => {}
        }
    }

    /// The value of a script expression in the page (promises awaited).
    pub fn eval(&mut self, expression: &str) -> anyhow::Result<Value> {
        let result = self.call(
            "Runtime.evaluate",
            json!({ "expression": expression, "returnByValue": true, "awaitPromise": true }),
        )?;
        if let Some(exception) = result.get("exceptionDetails") {
            bail!("evaluating {expression}: {exception}");
        }
        Ok(result["result"]["value"].clone())
    }

    /// Evaluates `expression` until it gives something other than null, false or undefined,
    /// and returns that; fails with `what` after `timeout`.
    pub fn wait_for(
        &mut self,
        what: &str,
        timeout: Duration,
        expression: &str,
    ) -> anyhow::Result<Value> {
        let start = Instant::now();
        loop {
            let value = self.eval(expression)?;
            if !(value.is_null() || value == Value::Bool(false)) {
                return Ok(value);
            }
            if start.elapsed() > timeout {
                bail!("timed out after {timeout:?} waiting for {what}");
            }
            std::thread::sleep(Duration::from_millis(100));
        }
    }

    /// A PNG of what the page shows now.
    pub fn screenshot(&mut self, path: &Path) -> anyhow::Result<()> {
        use base64::Engine as _;
        let shot = self.call("Page.captureScreenshot", json!({ "format": "png" }))?;
        let data = shot["data"].as_str().context("no screenshot data")?;
        let png = base64::engine::general_purpose::STANDARD.decode(data)?;
        if let Some(dir) = path.parent() {
            std::fs::create_dir_all(dir)?;
        }
        std::fs::write(path, png)?;
        Ok(())
    }

    /// The page's performance metrics (`Performance.getMetrics`), by name: `ScriptDuration`,
    /// `TaskDuration` (main-thread seconds), `JSHeapUsedSize`, ...
    pub fn metrics(&mut self) -> anyhow::Result<std::collections::BTreeMap<String, f64>> {
        let result = self.call("Performance.getMetrics", json!({}))?;
        Ok(result["metrics"]
            .as_array()
            .into_iter()
            .flatten()
            .filter_map(|m| Some((m["name"].as_str()?.to_owned(), m["value"].as_f64()?)))
            .collect())
    }
}

impl Drop for Browser {
    fn drop(&mut self) {
        let _ = self.child.kill();
        let _ = self.child.wait();
    }
}

/// The port Chromium chose, from the `DevToolsActivePort` file it writes into its profile.
fn devtools_port(profile: &Path, timeout: Duration) -> anyhow::Result<u16> {
    let file = profile.join("DevToolsActivePort");
    let start = Instant::now();
    loop {
        if let Ok(text) = std::fs::read_to_string(&file) {
            if let Some(port) = text.lines().next().and_then(|l| l.trim().parse().ok()) {
                return Ok(port);
            }
        }
        if start.elapsed() > timeout {
            bail!("Chromium wrote no {} within {timeout:?}", file.display());
        }
        std::thread::sleep(Duration::from_millis(50));
    }
}

/// A plain HTTP GET on loopback: the DevTools endpoint's list of targets. Its answer carries a
/// length and the connection may stay open, so the body is read to that length.
fn http_get(port: u16, path: &str) -> anyhow::Result<String> {
    let mut stream = TcpStream::connect(("127.0.0.1", port))?;
    stream.set_read_timeout(Some(Duration::from_secs(10)))?;
    write!(
        stream,
        "GET {path} HTTP/1.1\r\nHost: 127.0.0.1:{port}\r\nConnection: close\r\n\r\n"
    )?;
    let mut response = Vec::new();
    let mut chunk = [0u8; 4096];
    loop {
        let text = String::from_utf8_lossy(&response).into_owned();
        if let Some((head, body)) = text.split_once("\r\n\r\n") {
            let length = head
                .lines()
                .find_map(|l| {
                    let (name, value) = l.split_once(':')?;
                    name.eq_ignore_ascii_case("content-length")
                        .then(|| value.trim().parse::<usize>().ok())?
                })
                .context("an HTTP answer without a length")?;
            if body.len() >= length {
                return Ok(body[..length].to_owned());
            }
        }
        let n = stream.read(&mut chunk)?;
        if n == 0 {
            bail!("the HTTP answer ended early: {text:?}");
        }
        response.extend_from_slice(&chunk[..n]);
    }
}
