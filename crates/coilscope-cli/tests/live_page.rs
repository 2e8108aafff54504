//! `measure --serve`, the live page, in headless Chromium (installed by `.ci/run`),
//! driven through the DevTools protocol: during a virtual run the page loads, its plots
//! update (two screenshots differ, the page's block count grows, the curves arrive with their
//! bands), no console message of level error or uncaught exception appears, nothing but the
//! page's own server is asked for anything, and at the end the page links the report, which
//! the server serves.
use serde_json::{json, Value};
use std::io::{BufRead, BufReader};
use std::net::TcpStream;
use std::path::Path;
use std::process::{Child, Command, Stdio};
use std::time::{Duration, Instant};
use tungstenite::stream::MaybeTlsStream;
use tungstenite::{Message, WebSocket};

const CHROMIUM_FLAGS: [&str; 10] = [
    "--headless",
    "--no-sandbox",
    "--disable-gpu",
    "--disable-quic",
    "--no-first-run",
    "--disable-background-networking",
    "--disable-component-update",
    "--disable-sync",
    "--hide-scrollbars",
    "--remote-allow-origins=*",
];

fn chromium() -> String {
    let c = std::env::var("CHROMIUM").unwrap_or_else(|_| "/usr/bin/chromium".into());
    assert!(
        Path::new(&c).exists(),
        "headless Chromium not found at {c}: `.ci/run` installs Debian's chromium (or set CHROMIUM)"
    );
    c
}

/// Kills the child when the test ends, pass or fail.
struct Reaped(Child);
impl Drop for Reaped {
    fn drop(&mut self) {
        let _ = self.0.kill();
        let _ = self.0.wait();
    }
}

/// A DevTools-protocol client on one page session: commands answered in order, the events
/// in between kept.
struct Cdp {
    ws: WebSocket<MaybeTlsStream<TcpStream>>,
    id: u64,
    session: Option<String>,
    events: Vec<Value>,
}

impl Cdp {
    fn connect(url: &str) -> Cdp {
        let (ws, _) = tungstenite::connect(url).unwrap_or_else(|e| panic!("DevTools at {url}: {e}"));
        if let MaybeTlsStream::Plain(s) = ws.get_ref() {
            s.set_read_timeout(Some(Duration::from_millis(100))).unwrap();
        }
        Cdp { ws, id: 0, session: None, events: vec![] }
    }

    fn read(&mut self) -> Option<Value> {
        match self.ws.read() {
            Ok(Message::Text(t)) => Some(serde_json::from_str(&t).unwrap()),
            Ok(_) => None,
            Err(tungstenite::Error::Io(e))
                if matches!(e.kind(), std::io::ErrorKind::WouldBlock | std::io::ErrorKind::TimedOut) =>
            {
                None
            }
            Err(e) => panic!("DevTools connection: {e}"),
        }
    }

    fn call(&mut self, method: &str, params: Value) -> Value {
        self.id += 1;
        let mut m = json!({"id": self.id, "method": method, "params": params});
        if let Some(s) = &self.session {
            m["sessionId"] = json!(s);
        }
        self.ws.send(Message::text(m.to_string())).unwrap();
        let end = Instant::now() + Duration::from_secs(60);
        while Instant::now() < end {
            if let Some(v) = self.read() {
                if v["id"].as_u64() == Some(self.id) {
                    assert!(v.get("error").is_none(), "{method}: {v}");
                    return v["result"].clone();
                }
                self.events.push(v);
            }
        }
        panic!("{method}: no answer in 60 s");
    }

    /// Keep reading events for `d`.
    fn pump(&mut self, d: Duration) {
        let end = Instant::now() + d;
        while Instant::now() < end {
            if let Some(v) = self.read() {
                self.events.push(v);
            }
        }
    }

    fn eval(&mut self, js: &str) -> Value {
        let r = self.call("Runtime.evaluate", json!({"expression": js, "returnByValue": true, "awaitPromise": true}));
        assert!(r.get("exceptionDetails").is_none(), "{js}: {r}");
        r["result"]["value"].clone()
    }

    fn screenshot(&mut self) -> Vec<u8> {
        let r = self.call("Page.captureScreenshot", json!({"format": "png"}));
        decode_base64(r["data"].as_str().unwrap())
    }

    /// Console errors, uncaught exceptions and error log entries (failed loads among them).
    fn errors(&self) -> Vec<String> {
        self.events
            .iter()
            .filter(|e| match e["method"].as_str() {
                Some("Runtime.consoleAPICalled") => matches!(e["params"]["type"].as_str(), Some("error" | "assert")),
                Some("Runtime.exceptionThrown") => true,
                Some("Log.entryAdded") => e["params"]["entry"]["level"] == "error",
                _ => false,
            })
            .map(|e| e.to_string())
            .collect()
    }

    /// Every address the page asked for.
    fn requests(&self) -> Vec<String> {
        self.events
            .iter()
            .filter(|e| e["method"] == "Network.requestWillBeSent")
            .filter_map(|e| e["params"]["request"]["url"].as_str().map(str::to_string))
            .collect()
    }
}

fn decode_base64(s: &str) -> Vec<u8> {
    let val = |c: u8| match c {
        b'A'..=b'Z' => c - b'A',
        b'a'..=b'z' => c - b'a' + 26,
        b'0'..=b'9' => c - b'0' + 52,
        b'+' => 62,
        b'/' => 63,
        _ => panic!("not base64: {c}"),
    };
    let bytes: Vec<u8> = s.bytes().filter(|&c| c != b'=').map(val).collect();
    bytes
        .chunks(4)
        .flat_map(|c| {
            let n = c.iter().enumerate().fold(0u32, |a, (k, &v)| a | (v as u32) << (18 - 6 * k));
            [(n >> 16) as u8, (n >> 8) as u8, n as u8].into_iter().take(c.len() - 1)
        })
        .collect()
}

/// Headless Chromium with the DevTools protocol on a free port, attached to a new blank page
/// with the runtime, log, network and page domains on.
fn browser(profile: &Path) -> (Reaped, Cdp) {
    let child = Command::new(chromium())
        .args(CHROMIUM_FLAGS)
        .arg(format!("--user-data-dir={}", profile.display()))
        .args(["--remote-debugging-port=0", "--window-size=1200,1800", "about:blank"])
        .stdout(Stdio::null())
        .stderr(Stdio::null())
        .spawn()
        .unwrap();
    let child = Reaped(child);
    let port_file = profile.join("DevToolsActivePort");
    let end = Instant::now() + Duration::from_secs(30);
    let text = loop {
        if let Ok(t) = std::fs::read_to_string(&port_file) {
            if t.lines().count() >= 2 {
                break t;
            }
        }
        assert!(Instant::now() < end, "Chromium wrote no DevToolsActivePort in 30 s");
        std::thread::sleep(Duration::from_millis(100));
    };
    let mut lines = text.lines();
    let (port, path) = (lines.next().unwrap(), lines.next().unwrap());
    let mut cdp = Cdp::connect(&format!("ws://127.0.0.1:{port}{path}"));
    let target =
        cdp.call("Target.createTarget", json!({"url": "about:blank"}))["targetId"].as_str().unwrap().to_string();
    let session = cdp.call("Target.attachToTarget", json!({"targetId": target, "flatten": true}))["sessionId"]
        .as_str()
        .unwrap()
        .to_string();
    cdp.session = Some(session);
    for domain in ["Runtime.enable", "Log.enable", "Network.enable", "Page.enable"] {
        cdp.call(domain, json!({}));
    }
    cdp.call(
        "Emulation.setDeviceMetricsOverride",
        json!({"width": 1200, "height": 1800, "deviceScaleFactor": 1, "mobile": false}),
    );
    (child, cdp)
}

#[test]
fn the_console_check_catches_a_broken_page() {
    // The negative control: the checks below must be able to fail.
    let dir = tempfile::tempdir().unwrap();
    let page = dir.path().join("bad.html");
    std::fs::write(&page, "<html><body><script>console.error('boom'); notDefined();</script><img src='http://192.0.2.1/x.png'></body></html>").unwrap();
    let (_c, mut cdp) = browser(&dir.path().join("profile"));
    cdp.call("Page.navigate", json!({"url": format!("file://{}", page.display())}));
    cdp.pump(Duration::from_secs(2));
    let errors = cdp.errors();
    assert!(errors.iter().any(|e| e.contains("boom")) && errors.iter().any(|e| e.contains("notDefined")), "{errors:?}");
    assert!(cdp.requests().iter().any(|u| u.starts_with("http://192.0.2.1")), "{:?}", cdp.requests());
}

#[test]
fn live_page_updates_during_a_virtual_run_and_links_the_report() {
    let dir = tempfile::tempdir().unwrap();
    let out = dir.path().join("sb17");
    // Four times real time: the SB17 run (about 35 s of measurement) takes about 10 s.
    let run = Command::new(env!("CARGO_BIN_EXE_coilscope"))
        .args([
            "measure",
            "--virtual",
            "sb17cac35-4",
            "--out",
            out.to_str().unwrap(),
            "--serve",
            "127.0.0.1:0",
            "--pace",
            "4",
            "--serve-linger",
            "120",
        ])
        .stdout(Stdio::null())
        .stderr(Stdio::piped())
        .spawn()
        .unwrap();
    let mut run = Reaped(run);
    // The address is on stderr; the rest of stderr is drained so the run never blocks on it.
    let (tx, rx) = std::sync::mpsc::channel();
    let stderr = run.0.stderr.take().unwrap();
    std::thread::spawn(move || {
        for line in BufReader::new(stderr).lines().map_while(Result::ok) {
            let _ = tx.send(line);
        }
    });
    let url = loop {
        let line = rx.recv_timeout(Duration::from_secs(60)).expect("no `live page:` line in 60 s");
        if let Some(u) = line.strip_prefix("live page: ").filter(|u| u.starts_with("http://")) {
            break u.trim().to_string();
        }
    };
    assert!(url.starts_with("http://127.0.0.1:"), "{url}");

    let (_chromium, mut cdp) = browser(&dir.path().join("profile"));
    cdp.call("Page.navigate", json!({"url": url}));
    cdp.pump(Duration::from_millis(2500));
    let first = cdp.screenshot();
    let s1 = cdp.eval(
        "({blocks: coilscopeLive.blocks.length, frames: coilscopeLive.frames, traces: coilscopeLive.traces.length})",
    );
    cdp.pump(Duration::from_millis(2500));
    let second = cdp.screenshot();
    let s2 = cdp.eval("({blocks: coilscopeLive.blocks.length, frames: coilscopeLive.frames, traces: coilscopeLive.traces.length, bands: coilscopeLive.est ? Object.keys(coilscopeLive.est.bands).join(',') : '', t: coilscopeLive.blocks[coilscopeLive.blocks.length - 1].t})");
    std::fs::write(dir.path().join("first.png"), &first).unwrap();
    std::fs::write(dir.path().join("second.png"), &second).unwrap();
    if let Ok(keep) = std::env::var("COILSCOPE_KEEP_SHOTS") {
        std::fs::copy(dir.path().join("first.png"), Path::new(&keep).join("live_first.png")).unwrap();
        std::fs::copy(dir.path().join("second.png"), Path::new(&keep).join("live_second.png")).unwrap();
    }
    assert!(first.starts_with(b"\x89PNG") && second.starts_with(b"\x89PNG"));
    assert_ne!(first, second, "the page did not change in 2.5 s of a running measurement");
    let (b1, b2) = (s1["blocks"].as_u64().unwrap(), s2["blocks"].as_u64().unwrap());
    assert!(b1 > 0 && b2 > b1, "blocks {s1} -> {s2}");
    assert!(s2["frames"].as_u64().unwrap() > s1["frames"].as_u64().unwrap(), "{s1} -> {s2}");
    assert!(s2["traces"].as_u64().unwrap() > 10, "{s2}");
    // By then (about 20 s of measurement) the estimator has updated: the curves with bands.
    assert_eq!(s2["bands"], "Bl,Kms,Le", "{s2}");
    // The canvases are drawn (a blank canvas is one colour).
    let drawn = cdp.eval("[...document.querySelectorAll('canvas')].filter(c => { const d = c.getContext('2d').getImageData(0, 0, c.width, c.height).data; for (let k = 4; k < d.length; k += 4) if (d[k] !== d[0] || d[k+1] !== d[1] || d[k+2] !== d[2] || d[k+3] !== d[3]) return true; return false; }).length");
    assert_eq!(drawn, json!(13), "canvases with something drawn");

    // The end of the run: the page says so and links the report, which its server serves.
    let end = Instant::now() + Duration::from_secs(120);
    let report = loop {
        let r = cdp.eval("coilscopeLive.done ? (coilscopeLive.done.report || 'none') : ''");
        if r != "" {
            break r;
        }
        assert!(Instant::now() < end, "the run did not end in 120 s");
        cdp.pump(Duration::from_millis(500));
    };
    assert_eq!(report, "/report/report.html");
    let link = cdp.eval("document.querySelector('#done a').getAttribute('href')");
    assert_eq!(link, "/report/report.html");
    assert_eq!(cdp.eval("fetch('/report/report.html').then(r => r.status)"), 200);
    assert_eq!(cdp.eval("fetch('/report/report_files/bl.png').then(r => r.headers.get('content-type'))"), "image/png");
    assert_eq!(cdp.eval("fetch('/report/..%2F..%2Fetc%2Fpasswd').then(r => r.status)"), 400);
    let status = cdp.eval("coilscopeLive.done.status");
    assert_eq!(status, "converged");
    cdp.pump(Duration::from_millis(300));

    let errors: Vec<String> = cdp.errors().into_iter().filter(|e| !e.contains("/report/..")).collect();
    assert!(errors.is_empty(), "console errors: {errors:?}");
    // Everything the page asked for came from its own server: no CDN, no other host.
    let origin = url.trim_end_matches('/');
    let foreign: Vec<String> =
        cdp.requests().into_iter().filter(|u| !u.starts_with(origin) && !u.starts_with("data:")).collect();
    assert!(foreign.is_empty(), "requests elsewhere: {foreign:?}");
}
