//! # The live page of a measurement
//!
//! `coilscope measure --serve ADDR` starts a [`LiveServer`]: a small HTTP server (axum) on its
//! own thread that serves one self-contained page (HTML, CSS and JavaScript embedded in the
//! binary: no CDN, no network) and streams the measurement to it as server-sent events.
//!
//! The server is an **observer** of the measurement engine, like the terminal line and the run
//! database: the measurement loop hands it every block ([`LiveServer::block`]) and the end of
//! the run ([`LiveServer::done`]); nothing on the page can change the measurement (the server
//! has no route that takes input).
//!
//! ## Events (`GET /events`, `text/event-stream`, one JSON object per event, SI units)
//!
//! Every event has `kind` and `seq` (increasing from 1; a client ignores a `seq` it has seen,
//! so a reconnect that replays the history is harmless).
//!
//! | kind | fields |
//! |---|---|
//! | `info` | `device`, `excitation`, `controllable` (false for a replay), `fs` (Hz) |
//! | `block` | `t` (s, end of the block), `stage`, `volts` (V rms), `f_hp` (Hz), `x` (`[min, max]`,
//! m), `x_limit` (m or null), `dtv` (K), `re` (ohm), `residual`, `limited_by`, `eta` (s to the
//! expected convergence, or null while the level moves), `end` (s, when the run stops at the
//! latest), `update` (the window
//! residual of an update after this block, or null), `change` (`[Bl/Kms, Le]` relative change since
//! the previous update, or null), `distortion` (`{x, i, p}`: `[Bl, Kms, Le]` factors, or null) |
//! | `trace` | `t` (s, end of the block), `dt` (s per bin), `u` (V), `i` (A), `x` (m), `v` (m/s):
//! each a list of `[min, max]` per bin |
//! | `estimate` | `t`, `bands`: `{Bl, Kms, Le}`, each `{x, value, sd}` over the estimator's reach |
//! | `done` | `status`, `message`, `report` (the report's address on this server, or null) |
//!
//! A page that connects late first gets the history: every `block`, the last
//! [`RECENT_TRACES`] traces, the latest `estimate` and `done`.

use axum::extract::{Path as UrlPath, State};
use axum::http::{header, StatusCode};
use axum::response::sse::{Event, KeepAlive, Sse};
use axum::response::{Html, IntoResponse, Response};
use axum::routing::get;
use axum::Router;
use coilscope_measure::Live;
use futures_util::stream::{self, Stream, StreamExt};
use serde_json::{json, Value};
use std::collections::VecDeque;
use std::convert::Infallible;
use std::net::SocketAddr;
use std::path::{Path, PathBuf};
use std::sync::{Arc, Mutex};
use tokio::sync::broadcast;

/// The page (one file: markup, style and script).
pub const PAGE: &str = include_str!("page.html");
/// Traces a late page gets (at the engine's 0.1 s blocks: the last 10 s).
pub const RECENT_TRACES: usize = 100;
/// The default address of `--serve`.
pub const DEFAULT_ADDR: &str = "127.0.0.1:8640";

#[derive(Default)]
struct History {
    seq: u64,
    info: Option<Arc<str>>,
    blocks: Vec<Arc<str>>,
    traces: VecDeque<Arc<str>>,
    estimate: Option<Arc<str>>,
    done: Option<Arc<str>>,
    /// The output directory whose report the page links, once the run is done.
    report_dir: Option<PathBuf>,
}

struct Hub {
    history: Mutex<History>,
    tx: broadcast::Sender<Arc<str>>,
}

impl Hub {
    fn lock(&self) -> std::sync::MutexGuard<'_, History> {
        // A panic elsewhere while holding the lock leaves plain data behind: keep serving it.
        self.history.lock().unwrap_or_else(|e| e.into_inner())
    }

    /// Number the event, keep it in the history (`keep`) and send it to the open pages.
    fn publish(&self, mut v: Value, keep: impl FnOnce(&mut History, Arc<str>)) {
        let mut h = self.lock();
        h.seq += 1;
        v["seq"] = json!(h.seq);
        let text: Arc<str> = v.to_string().into();
        keep(&mut h, text.clone());
        // No page open is not an error.
        let _ = self.tx.send(text);
    }

    /// The history in the order it was published, and a receiver for what follows (taken
    /// under the same lock: nothing is lost or sent twice between the two).
    fn subscribe(&self) -> (Vec<Arc<str>>, broadcast::Receiver<Arc<str>>) {
        let h = self.lock();
        let rx = self.tx.subscribe();
        let mut all: Vec<Arc<str>> =
            h.info.iter().chain(&h.blocks).chain(&h.traces).chain(&h.estimate).chain(&h.done).cloned().collect();
        all.sort_by_key(|e| seq_of(e));
        (all, rx)
    }
}

fn seq_of(e: &str) -> u64 {
    serde_json::from_str::<Value>(e).ok().and_then(|v| v["seq"].as_u64()).unwrap_or(0)
}

/// The live page's server: started before the measurement, fed by its loop, stopped (or
/// dropped) after it.
pub struct LiveServer {
    addr: SocketAddr,
    hub: Arc<Hub>,
    stop: Option<tokio::sync::oneshot::Sender<()>>,
    thread: Option<std::thread::JoinHandle<()>>,
}

impl LiveServer {
    /// Bind `addr` and serve on a thread of its own. A non-loopback address is refused unless
    /// `public` (the page shows the measurement to anyone who can reach the port). Port 0
    /// picks a free port: [`LiveServer::url`] says which.
    pub fn start(addr: &str, public: bool) -> Result<Self, String> {
        let parsed: SocketAddr = addr
            .parse()
            .map_err(|_| format!("--serve {addr}: not an address; give IP:PORT, for example {DEFAULT_ADDR}"))?;
        if !parsed.ip().is_loopback() && !public {
            return Err(format!("--serve {addr}: {} is not a loopback address; the live page shows the measurement to anyone who can reach it. Add --serve-public to serve it there, or use 127.0.0.1", parsed.ip()));
        }
        let listener = std::net::TcpListener::bind(parsed).map_err(|e| {
            format!("--serve {addr}: cannot listen there ({e}); choose another port, or 0 for a free one")
        })?;
        listener.set_nonblocking(true).map_err(|e| format!("--serve {addr}: {e}"))?;
        let bound = listener.local_addr().map_err(|e| format!("--serve {addr}: {e}"))?;
        let (tx, _) = broadcast::channel(1024);
        let hub = Arc::new(Hub { history: Mutex::new(History::default()), tx });
        let app = Router::new()
            .route("/", get(|| async { Html(PAGE) }))
            .route("/events", get(events))
            .route("/report/{*file}", get(report_file))
            .with_state(hub.clone());
        let (stop_tx, stop_rx) = tokio::sync::oneshot::channel::<()>();
        let rt = tokio::runtime::Builder::new_current_thread()
            .enable_io()
            .enable_time()
            .build()
            .map_err(|e| format!("--serve: cannot start the server's runtime: {e}"))?;
        let thread = std::thread::Builder::new()
            .name("coilscope-live".into())
            .spawn(move || {
                rt.block_on(async move {
                    let listener = match tokio::net::TcpListener::from_std(listener) {
                        Ok(l) => l,
                        Err(e) => {
                            eprintln!("warning: the live page stopped: {e}");
                            return;
                        }
                    };
                    let serve = std::pin::pin!(std::future::IntoFuture::into_future(axum::serve(listener, app)));
                    // Stopping drops the open event streams with the runtime: a graceful
                    // shutdown would wait for pages that never close them.
                    let _ = futures_util::future::select(serve, stop_rx).await;
                })
            })
            .map_err(|e| format!("--serve: cannot start the server's thread: {e}"))?;
        Ok(LiveServer { addr: bound, hub, stop: Some(stop_tx), thread: Some(thread) })
    }

    /// The address actually bound.
    pub fn addr(&self) -> SocketAddr {
        self.addr
    }

    /// The page's address.
    pub fn url(&self) -> String {
        format!("http://{}/", self.addr)
    }

    /// What is measured, before the first block.
    pub fn info(&self, device: &str, excitation: &str, controllable: bool, fs: f64) {
        self.hub.publish(
            json!({"kind": "info", "device": device, "excitation": excitation, "controllable": controllable, "fs": fs}),
            |h, e| h.info = Some(e),
        );
    }

    /// One block of the measurement (call it from the engine's observer).
    pub fn block(&self, l: &Live) {
        self.hub.publish(block_event(l), |h, e| h.blocks.push(e));
        if !l.trace.u.is_empty() {
            self.hub.publish(trace_event(l), |h, e| {
                h.traces.push_back(e);
                if h.traces.len() > RECENT_TRACES {
                    h.traces.pop_front();
                }
            });
        }
        if !l.bands.is_empty() {
            let bands: serde_json::Map<String, Value> =
                l.bands.iter().map(|(k, b)| (k.to_string(), json!({"x": b.x, "value": b.value, "sd": b.sd}))).collect();
            self.hub.publish(json!({"kind": "estimate", "t": l.t, "bands": bands}), |h, e| h.estimate = Some(e));
        }
    }

    /// The run is over: its status and message, and the directory holding `report.html`
    /// (served under `/report/`) if one was written.
    pub fn done(&self, status: &str, message: &str, report_dir: Option<&Path>) {
        let report = report_dir.filter(|d| d.join("report.html").is_file());
        self.hub.lock().report_dir = report.map(Path::to_path_buf);
        let link = report.map(|_| "/report/report.html");
        self.hub.publish(json!({"kind": "done", "status": status, "message": message, "report": link}), |h, e| {
            h.done = Some(e)
        });
    }

    /// Stop serving (also on drop).
    pub fn stop(mut self) {
        self.shutdown();
    }

    fn shutdown(&mut self) {
        if let Some(s) = self.stop.take() {
            let _ = s.send(());
        }
        if let Some(t) = self.thread.take() {
            let _ = t.join();
        }
    }
}

impl Drop for LiveServer {
    fn drop(&mut self) {
        self.shutdown();
    }
}

/// A block's scalars.
pub fn block_event(l: &Live) -> Value {
    json!({
        "kind": "block",
        "t": l.t,
        "stage": l.stage.name(),
        "volts": l.volts,
        "f_hp": l.f_hp,
        "x": [l.x_min, l.x_max],
        "x_limit": l.x_limit,
        "dtv": l.dtv,
        "re": l.re,
        "residual": l.residual,
        "limited_by": l.limited_by.to_string(),
        "eta": l.eta,
        "end": l.end,
        "update": l.update,
        "change": l.change.map(|(a, b)| [a, b]),
        "distortion": l.distortion.map(|c| json!({"x": c.x, "i": c.i, "p": c.p})),
    })
}

/// A block's signal envelopes.
pub fn trace_event(l: &Live) -> Value {
    let tr = &l.trace;
    json!({"kind": "trace", "t": l.t, "dt": tr.dt, "u": tr.u, "i": tr.i, "x": tr.x, "v": tr.v})
}

async fn events(State(hub): State<Arc<Hub>>) -> Sse<impl Stream<Item = Result<Event, Infallible>>> {
    let (history, rx) = hub.subscribe();
    let live = stream::unfold(rx, |mut rx| async move {
        match rx.recv().await {
            Ok(e) => Some((e, rx)),
            // A page too slow to keep up (or the end of the run) closes the stream; the
            // browser reconnects and gets the history again.
            Err(_) => None,
        }
    });
    let all = stream::iter(history).chain(live).map(|e| Ok(Event::default().data(&*e)));
    Sse::new(all).keep_alive(KeepAlive::default())
}

/// A file of the written report (`report.html`, its `report_files/`), once the run is done.
async fn report_file(State(hub): State<Arc<Hub>>, UrlPath(file): UrlPath<String>) -> Response {
    let Some(dir) = hub.lock().report_dir.clone() else {
        return (StatusCode::NOT_FOUND, "no report yet: it is written when the measurement ends").into_response();
    };
    match safe_join(&dir, &file) {
        Some(path) => match std::fs::read(&path) {
            Ok(bytes) => ([(header::CONTENT_TYPE, content_type(&path))], bytes).into_response(),
            Err(_) => (StatusCode::NOT_FOUND, format!("{file}: not in the report")).into_response(),
        },
        None => (StatusCode::BAD_REQUEST, format!("{file}: not a file of the report")).into_response(),
    }
}

/// `dir/file` when `file` is a plain relative path (no `..`, no root): the page can read the
/// report and nothing else on the machine.
pub fn safe_join(dir: &Path, file: &str) -> Option<PathBuf> {
    let rel = Path::new(file);
    rel.components().all(|c| matches!(c, std::path::Component::Normal(_))).then(|| dir.join(rel))
}

fn content_type(p: &Path) -> &'static str {
    match p.extension().and_then(|e| e.to_str()) {
        Some("html") => "text/html; charset=utf-8",
        Some("png") => "image/png",
        Some("svg") => "image/svg+xml",
        Some("csv") => "text/csv; charset=utf-8",
        Some("json") => "application/json",
        _ => "application/octet-stream",
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn report_paths_stay_inside_the_report() {
        let d = Path::new("/tmp/run");
        assert_eq!(safe_join(d, "report.html"), Some(d.join("report.html")));
        assert_eq!(safe_join(d, "report_files/bl.png"), Some(d.join("report_files/bl.png")));
        for bad in ["../etc/passwd", "report_files/../../x", "/etc/passwd", ""] {
            assert_eq!(safe_join(d, bad).filter(|_| !bad.is_empty()), None, "{bad}");
        }
    }

    #[test]
    fn the_page_loads_nothing_from_elsewhere() {
        // Every script and style is inline: no src= or href= to another host, no import.
        let lower = PAGE.to_lowercase();
        for bad in ["src=\"http", "href=\"http", "src='http", "@import", "<script src", "fetch(\"http"] {
            assert!(!lower.contains(bad), "the page refers to {bad}");
        }
    }

    #[test]
    fn non_loopback_needs_the_public_flag() {
        let e = LiveServer::start("0.0.0.0:0", false).err().expect("refused");
        assert!(e.contains("--serve-public") && e.contains("0.0.0.0"), "{e}");
        let e = LiveServer::start("localhost", false).err().expect("refused");
        assert!(e.contains("IP:PORT"), "{e}");
    }

    #[test]
    fn late_subscriber_gets_the_history_in_order_and_nothing_twice() {
        let s = LiveServer::start("127.0.0.1:0", false).unwrap();
        s.info("virtual", "noise", true, 48000.0);
        let (hist0, _) = s.hub.subscribe();
        assert_eq!(hist0.len(), 1);
        let (_, mut rx) = s.hub.subscribe();
        s.done("converged", "ok", None);
        let (hist, _) = s.hub.subscribe();
        let seqs: Vec<u64> = hist.iter().map(|e| seq_of(e)).collect();
        assert_eq!(seqs, vec![1, 2]);
        assert_eq!(seq_of(&rx.try_recv().unwrap()), 2);
        assert!(rx.try_recv().is_err());
    }
}
