//! `stitch run --console`: the surgeon's seat in a browser, served by the binary itself.
//!
//! The engine runs on its own thread and never waits on a viewer: it appends each journal
//! record to the [`Hub`] (a `Vec` behind a mutex) and bumps a counter; every viewer's task
//! sends the records it has not yet sent, at its own speed. Events are never dropped for a
//! slow viewer; it only falls behind. Commands come back through a channel the supervisor
//! polls every [`stitch_engine::LIVE_POLL`] while a step moves.
//!
//! Locked: the server binds loopback unless told otherwise; every command and stream checks
//! the `Host` (DNS rebinding) and `Origin` (another site's page) headers and the per-run
//! token (`Authorization: Bearer`, or the stream's first message); one viewer is in control
//! at a time. Every refused command goes to the run's journal ([`Entry::Refused`]).
//!
//! [`Entry::Refused`]: stitch_engine::Entry::Refused

use axum::extract::ws::{Message, WebSocket, WebSocketUpgrade};
use axum::extract::{ConnectInfo, State};
use axum::http::{HeaderMap, StatusCode, header};
use axum::response::{IntoResponse, Response};
use axum::routing::{get, post};
use serde::Deserialize;
use serde_json::{Value, json};
use std::net::SocketAddr;
use std::sync::mpsc::{Receiver, Sender};
use std::sync::{Arc, Mutex, OnceLock, PoisonError};
use std::time::Duration;
use stitch_engine::{JournalSink, Op, Plan, Record, Refusal, SupervisorCommand};
use tokio::sync::watch;

/// The page and its script and style, embedded (nothing fetched at run time).
const INDEX_HTML: &str = include_str!("../web/index.html");
const APP_JS: &str = include_str!("../web/app.js");
const APP_CSS: &str = include_str!("../web/app.css");

/// Strict: the page's own script and style only, no inline code, nothing from elsewhere.
const CSP: &str = "default-src 'none'; script-src 'self'; style-src 'self'; img-src 'self' blob:; \
                   connect-src 'self'; base-uri 'none'; form-action 'none'; frame-ancestors 'none'";

/// The most camera frames a second the console makes, for all its viewers.
const MAX_FRAME_HZ: f64 = 15.0;

/// A recorded frame: its log time (ns) and JPEG.
type RecordedFrame = (u64, Vec<u8>);

/// What the recorder drew on the left image at a log time (ns): lines and labels, as the page
/// draws them (`{"lines": [{"points", "color"}], "labels": [{"at", "text", "color"}]}`).
type RecordedDrawing = (u64, Value);

/// A camera frame for the page: the left view (JPEG) and what to draw over it, in its pixels.
pub struct Frame {
    /// The left image, JPEG.
    pub jpeg: Vec<u8>,
    /// `{"t_s", "width", "height", "needle": [[u, v], ...] | null, "confidence",
    /// "estimate_age_s", "jaws": [{"arm", "tip": [u, v], "back": [u, v]}]}`.
    pub overlay: Value,
}

/// Makes a frame when a viewer asks for one (off the engine's thread, changing nothing in
/// the run); `None` when there is nothing to show.
pub type FrameSource = Box<dyn FnMut() -> Option<Frame> + Send>;

/// How long a viewer has to send the token after opening the stream.
const TOKEN_WAIT: Duration = Duration::from_secs(5);

/// What the engine's side shares with the viewers' tasks.
pub struct Hub {
    state: Mutex<HubState>,
    /// Bumped on every change viewers must hear about (a record, the control, the end).
    changed: watch::Sender<u64>,
    token: String,
    /// The `Host` header values a request may carry (`127.0.0.1:8080`, `localhost:8080`, ...).
    hosts: Vec<String>,
    /// The plan as the page draws it.
    plan: Value,
    /// The explored state diagram's edges, once computed (off the engine's thread).
    diagram: OnceLock<Value>,
    commands: Mutex<Sender<(String, String)>>,
    /// Whether the person at the console answers the robot's requests for help (`done`,
    /// `failed`: on a real dVRK; on the mock the simulated surgeon does).
    answers_interventions: bool,
    /// Renders the left camera's view with its overlay, on request (one viewer at a time).
    frames: Mutex<Option<FrameSource>>,
    /// Playing a recording (`stitch console FILE`): its length and state, for the page; its
    /// left camera's frames (log time ns, JPEG).
    replay: Option<Value>,
    recorded_frames: Vec<RecordedFrame>,
    recorded_drawings: Vec<RecordedDrawing>,
    /// Whether the run will show a camera (frames may come a moment after the start).
    camera: std::sync::atomic::AtomicBool,
    /// When the last frame was made (frames are made at most [`MAX_FRAME_HZ`]).
    last_frame: Mutex<Option<std::time::Instant>>,
    refusals: Mutex<Sender<Refusal>>,
}

#[derive(Default)]
struct HubState {
    /// Every journal record so far, as JSON.
    events: Vec<Arc<str>>,
    /// The viewer in control, if any.
    control: Option<u64>,
    next_viewer: u64,
    /// Viewers connected now.
    viewers: usize,
    /// The run ended: viewers send what is left and close.
    ended: bool,
}

impl Hub {
    fn lock(&self) -> std::sync::MutexGuard<'_, HubState> {
        self.state.lock().unwrap_or_else(PoisonError::into_inner)
    }

    fn bump(&self) {
        self.changed.send_modify(|n| *n += 1);
    }

    fn refuse(&self, from: &str, command: &str, why: &str) {
        let _ = self
            .refusals
            .lock()
            .unwrap_or_else(PoisonError::into_inner)
            .send(Refusal {
                command: command.to_string(),
                from: from.to_string(),
                why: why.to_string(),
            });
    }

    /// Check `Host` and `Origin`: the reason to refuse, if any.
    fn check_origin(&self, headers: &HeaderMap) -> Option<String> {
        let host = headers.get(header::HOST).and_then(|h| h.to_str().ok());
        let Some(host) = host.filter(|h| self.hosts.iter().any(|a| a == h)) else {
            return Some(format!(
                "Host {:?} is not this console's (expected one of {})",
                host.unwrap_or(""),
                self.hosts.join(", ")
            ));
        };
        // Browsers send `Origin` with every POST and WebSocket; a client that is not a page
        // (a script, curl) sends none and cannot be steered by another site.
        match headers
            .get(header::ORIGIN)
            .map(|o| o.to_str().unwrap_or("?"))
        {
            Some(o) if o != format!("http://{host}") => Some(format!(
                "Origin {o:?} is not this console's (http://{host})"
            )),
            _ => None,
        }
    }

    fn token_ok(&self, given: &str) -> bool {
        // Compared in time independent of where they differ.
        let (a, b) = (given.as_bytes(), self.token.as_bytes());
        a.len() == b.len() && a.iter().zip(b).fold(0u8, |acc, (x, y)| acc | (x ^ y)) == 0
    }
}

/// What the engine's supervisor takes from the console.
pub struct Feeds {
    /// Commands from the viewer in control (and an e-stop from any viewer), as their words
    /// (`pause`, ..., and `done`, `failed` where the console answers interventions), with who
    /// sent them (`console viewer 3 (127.0.0.1:50412)`).
    pub commands: Receiver<(String, String)>,
    /// Another way into `commands` (the terminal's, on a real dVRK).
    #[cfg_attr(not(feature = "ros2"), allow(dead_code))] // a real dVRK is ROS 2's
    pub sender: Sender<(String, String)>,
    /// Commands refused, for the journal.
    pub refusals: Receiver<Refusal>,
}

/// A running console: dropped, it lets its viewers read the end and stops.
pub struct Console {
    hub: Arc<Hub>,
    addr: SocketAddr,
    stop: Option<tokio::sync::oneshot::Sender<()>>,
    thread: Option<std::thread::JoinHandle<()>>,
}

impl std::fmt::Debug for Console {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("Console")
            .field("addr", &self.addr)
            .finish_non_exhaustive()
    }
}

impl Console {
    /// Bind `addr` and serve the console for `plan` on a thread of its own. A non-loopback
    /// address is refused unless `remote`.
    /// `person`: the console's person answers the robot's requests for help (a real dVRK).
    pub fn start(
        addr: SocketAddr,
        remote: bool,
        plan: &Arc<Plan>,
        person: bool,
    ) -> anyhow::Result<(Self, Feeds)> {
        Self::open(addr, remote, plan, person, None)
    }

    /// Serve a recorded run (`stitch console FILE`): its journal and camera frames, with a
    /// timeline to scrub; no commands.
    pub fn replay(
        addr: SocketAddr,
        remote: bool,
        playback: crate::replay::Playback,
    ) -> anyhow::Result<Self> {
        let plan = Arc::new(playback.plan);
        let end_s = playback.records.last().map_or(0.0, |r| r.t_s);
        let info = json!({ "duration_s": end_s, "complete": playback.complete, "frames": playback.frames.len() });
        let drawings = playback
            .annotations
            .iter()
            .map(|(t, a)| (*t, drawing(a)))
            .collect();
        let (console, _) = Self::open(
            addr,
            remote,
            &plan,
            false,
            Some((info, playback.frames, drawings)),
        )?;
        {
            let mut state = console.hub.lock();
            for r in &playback.records {
                state.events.push(record_json(r));
            }
        }
        console.hub.bump();
        Ok(console)
    }

    fn open(
        addr: SocketAddr,
        remote: bool,
        plan: &Arc<Plan>,
        person: bool,
        replay: Option<(Value, Vec<RecordedFrame>, Vec<RecordedDrawing>)>,
    ) -> anyhow::Result<(Self, Feeds)> {
        if !addr.ip().is_loopback() && !remote {
            anyhow::bail!(
                "--console {addr}: not a loopback address; anyone who can reach it could open \
                 the page (the run's events and commands still need the token). Add \
                 --console-remote to serve it there anyway"
            );
        }
        if addr.ip().is_unspecified() {
            anyhow::bail!(
                "--console {addr}: give the address of the interface to serve on (e.g. \
                 192.168.1.5:{}), not every interface: the console accepts only requests whose \
                 Host is the address it was given (or loopback)",
                addr.port()
            );
        }
        let listener = std::net::TcpListener::bind(addr)
            .map_err(|e| anyhow::anyhow!("--console {addr}: cannot listen there: {e}"))?;
        listener.set_nonblocking(true)?;
        let addr = listener.local_addr()?;
        if !addr.ip().is_loopback() {
            eprintln!(
                "WARNING: the console listens on {addr}, not loopback: anyone on that network \
                 can open the page; only the token keeps them from watching the run and \
                 commanding the robot. The traffic, token included, is not encrypted."
            );
        }
        let port = addr.port();
        let mut hosts = vec![
            format!("127.0.0.1:{port}"),
            format!("localhost:{port}"),
            format!("[::1]:{port}"),
        ];
        if !addr.ip().is_loopback() {
            hosts.push(addr.to_string());
        }
        let (commands, command_rx) = std::sync::mpsc::channel();
        let (refusals, refusal_rx) = std::sync::mpsc::channel();
        let hub = Arc::new(Hub {
            state: Mutex::new(HubState::default()),
            changed: watch::channel(0).0,
            token: token()?,
            hosts,
            plan: plan_json(plan),
            diagram: OnceLock::new(),
            commands: Mutex::new(commands.clone()),
            answers_interventions: person,
            frames: Mutex::new(None),
            camera: std::sync::atomic::AtomicBool::new(
                replay.as_ref().is_some_and(|(_, f, _)| !f.is_empty()),
            ),
            recorded_frames: replay
                .as_ref()
                .map(|(_, f, _)| f.clone())
                .unwrap_or_default(),
            recorded_drawings: replay
                .as_ref()
                .map(|(_, _, d)| d.clone())
                .unwrap_or_default(),
            replay: replay.map(|(info, _, _)| info),
            last_frame: Mutex::new(None),
            refusals: Mutex::new(refusals),
        });
        // The state diagram: the explorer's edges, computed off the engine's thread.
        {
            let (hub, plan) = (Arc::clone(&hub), Arc::clone(plan));
            std::thread::spawn(move || {
                let options = stitch_engine::ExploreOptions {
                    max_commands: 1,
                    ..stitch_engine::ExploreOptions::default()
                };
                let found = stitch_engine::explore(plan, options);
                let edges: Vec<Value> = found.edges.keys().map(|(a, b)| json!([a, b])).collect();
                let _ = hub.diagram.set(Value::Array(edges));
                hub.bump();
            });
        }
        let (stop, stopped) = tokio::sync::oneshot::channel::<()>();
        let app = axum::Router::new()
            .route("/", get(index))
            .route("/app.js", get(app_js))
            .route("/app.css", get(app_css))
            .route("/api/stream", get(stream))
            .route("/api/command", post(command))
            .route("/api/control", post(control))
            .with_state(Arc::clone(&hub));
        let runtime = tokio::runtime::Builder::new_current_thread()
            .enable_all()
            .build()?;
        let thread = std::thread::Builder::new()
            .name("console".into())
            .spawn(move || {
                runtime.block_on(async move {
                    let listener = match tokio::net::TcpListener::from_std(listener) {
                        Ok(l) => l,
                        Err(e) => {
                            eprintln!("the console stopped: {e}");
                            return;
                        }
                    };
                    let serve = axum::serve(
                        listener,
                        app.into_make_service_with_connect_info::<SocketAddr>(),
                    )
                    .with_graceful_shutdown(async move {
                        let _ = stopped.await;
                    });
                    if let Err(e) = serve.await {
                        eprintln!("the console stopped: {e}");
                    }
                });
            })?;
        Ok((
            Self {
                hub,
                addr,
                stop: Some(stop),
                thread: Some(thread),
            },
            Feeds {
                commands: command_rx,
                sender: commands,
                refusals: refusal_rx,
            },
        ))
    }

    /// Where to open it, token included (in the fragment: never sent to a server).
    pub fn url(&self) -> String {
        format!("http://{}/#token={}", self.addr, self.hub.token)
    }

    /// The journal's sink: every record, as it is journaled.
    pub fn sink(&self) -> JournalSink {
        let hub = Arc::clone(&self.hub);
        Box::new(move |r: &Record| {
            hub.lock().events.push(record_json(r));
            hub.bump();
        })
    }
}

impl Drop for Console {
    fn drop(&mut self) {
        self.hub.lock().ended = true;
        self.hub.bump();
        // Viewers get a moment to read the end; then the server stops.
        let deadline = std::time::Instant::now() + Duration::from_millis(500);
        while self.hub.lock().viewers > 0 && std::time::Instant::now() < deadline {
            std::thread::sleep(Duration::from_millis(10));
        }
        if let Some(stop) = self.stop.take() {
            let _ = stop.send(());
        }
        if let Some(t) = self.thread.take() {
            let _ = t.join();
        }
    }
}

/// The next frame, at most [`MAX_FRAME_HZ`] for all viewers together (a blocking task).
fn make_frame(hub: &Hub) -> Option<Frame> {
    let mut source = hub.frames.lock().unwrap_or_else(PoisonError::into_inner);
    let source = source.as_mut()?;
    {
        let mut last = hub
            .last_frame
            .lock()
            .unwrap_or_else(PoisonError::into_inner);
        let period = Duration::from_secs_f64(1.0 / MAX_FRAME_HZ);
        if let Some(wait) = last.map(|l| period.saturating_sub(l.elapsed())) {
            std::thread::sleep(wait);
        }
        *last = Some(std::time::Instant::now());
    }
    source()
}

/// A journal record as the page gets it.
fn record_json(r: &Record) -> Arc<str> {
    serde_json::to_string(r)
        .unwrap_or_else(|e| format!("{{\"error\":\"record {}: {e}\"}}", r.seq))
        .into()
}

/// A recorded run's frame at `t_s` (the last one at or before it; the first one before
/// any), with what the recorder drew on the left image last by then (the estimate, and the
/// truth on the mock).
fn recorded_frame(
    frames: &[RecordedFrame],
    drawings: &[RecordedDrawing],
    t_s: f64,
) -> Option<Frame> {
    let t = (t_s.max(0.0) * 1e9) as u64;
    let i = frames.partition_point(|(ft, _)| *ft <= t).saturating_sub(1);
    let (ft, jpeg) = frames.get(i)?;
    let drawn = drawings
        .partition_point(|(dt, _)| *dt <= t)
        .checked_sub(1)
        .and_then(|k| drawings.get(k));
    let mut overlay = json!({ "t_s": *ft as f64 * 1e-9, "needle": null, "jaws": [] });
    if let Some((dt, d)) = drawn {
        overlay["drawn"] = d.clone();
        overlay["drawn_t_s"] = json!(*dt as f64 * 1e-9);
    }
    Some(Frame {
        jpeg: jpeg.clone(),
        overlay,
    })
}

/// What the recorder drew, as the page draws it: line strips and labels, colours as CSS.
fn drawing(a: &stitch_recorder::ImageAnnotations) -> Value {
    let css = |c: &stitch_recorder::Color| {
        format!(
            "rgba({}, {}, {}, {})",
            (c.r * 255.0).round(),
            (c.g * 255.0).round(),
            (c.b * 255.0).round(),
            c.a
        )
    };
    let lines: Vec<Value> = a
        .points
        .iter()
        .map(|p| {
            json!({
                "points": p.points.iter().map(|q| [q.x, q.y]).collect::<Vec<_>>(),
                "color": css(&p.outline_color),
            })
        })
        .collect();
    let labels: Vec<Value> = a
        .texts
        .iter()
        .map(|t| json!({ "at": [t.position.x, t.position.y], "text": t.text, "color": css(&t.text_color) }))
        .collect();
    json!({ "lines": lines, "labels": labels })
}

/// A per-run token: 128 bits from the operating system's generator (no console without it:
/// a guessable token guards nothing).
fn token() -> anyhow::Result<String> {
    use rand::TryRngCore;
    let mut bytes = [0u8; 16];
    rand::rngs::OsRng.try_fill_bytes(&mut bytes).map_err(|e| {
        anyhow::anyhow!("the console's token: no random bytes from the system: {e}")
    })?;
    Ok(bytes.iter().map(|b| format!("{b:02x}")).collect())
}

/// The plan as the page draws it: each throw's program, one line per operation.
fn plan_json(plan: &Plan) -> Value {
    let throws: Vec<Value> = plan
        .throws
        .iter()
        .enumerate()
        .map(|(i, t)| {
            let ops: Vec<Value> = t
                .program
                .iter()
                .enumerate()
                .filter_map(|(k, op)| {
                    let (kind, label) = match op {
                        Op::Do(s) => ("step", s.kind.name().to_string()),
                        Op::Branch { cond, role, .. } => ("branch", format!("{role:?} {cond}")),
                        Op::Checkpoint { label, .. } => {
                            ("checkpoint", format!("checkpoint: {label}"))
                        }
                        Op::Jump { .. } => return None,
                    };
                    Some(json!({ "step": k, "kind": kind, "label": label }))
                })
                .collect();
            json!({ "throw": i, "point": t.point.index, "ops": ops })
        })
        .collect();
    json!({
        "name": plan.name,
        "file": plan.file,
        "interventions": plan.interventions,
        "thread_length_m": plan.thread_length_m,
        "throws": throws,
    })
}

async fn index() -> Response {
    asset(INDEX_HTML, "text/html; charset=utf-8")
}

async fn app_js() -> Response {
    asset(APP_JS, "text/javascript; charset=utf-8")
}

async fn app_css() -> Response {
    asset(APP_CSS, "text/css; charset=utf-8")
}

fn asset(body: &'static str, ty: &'static str) -> Response {
    (
        [
            (header::CONTENT_TYPE, ty),
            (header::CONTENT_SECURITY_POLICY, CSP),
            (header::X_CONTENT_TYPE_OPTIONS, "nosniff"),
            (header::CACHE_CONTROL, "no-store"),
        ],
        body,
    )
        .into_response()
}

fn refused(status: StatusCode, why: &str) -> Response {
    (status, axum::Json(json!({ "refused": why }))).into_response()
}

/// The bearer token of a request, if it carries one.
fn bearer(headers: &HeaderMap) -> Option<&str> {
    headers
        .get(header::AUTHORIZATION)?
        .to_str()
        .ok()?
        .strip_prefix("Bearer ")
}

/// Host, Origin and token: the refusal, journaled, if any fails.
fn guard(hub: &Hub, headers: &HeaderMap, from: &str, what: &str) -> Result<(), Box<Response>> {
    if let Some(why) = hub.check_origin(headers) {
        hub.refuse(from, what, &why);
        return Err(Box::new(refused(StatusCode::FORBIDDEN, &why)));
    }
    match bearer(headers) {
        None => {
            let why = "no token (Authorization: Bearer <the token printed at start>)";
            hub.refuse(from, what, why);
            Err(Box::new(refused(StatusCode::UNAUTHORIZED, why)))
        }
        Some(t) if !hub.token_ok(t) => {
            let why = "wrong token";
            hub.refuse(from, what, why);
            Err(Box::new(refused(StatusCode::UNAUTHORIZED, why)))
        }
        Some(_) => Ok(()),
    }
}

#[derive(Deserialize)]
struct CommandBody {
    command: String,
    #[serde(default)]
    viewer: Option<u64>,
}

/// `POST /api/command {"command": "pause", "viewer": 3}`.
async fn command(
    State(hub): State<Arc<Hub>>,
    ConnectInfo(peer): ConnectInfo<SocketAddr>,
    headers: HeaderMap,
    body: axum::body::Bytes,
) -> Response {
    let from = format!("console {peer}");
    let parsed: Result<CommandBody, _> = serde_json::from_slice(&body);
    let what = parsed.as_ref().map_or_else(
        |_| String::from_utf8_lossy(&body).into_owned(),
        |b| b.command.clone(),
    );
    if let Err(r) = guard(&hub, &headers, &from, &what) {
        return *r;
    }
    let body = match parsed {
        Ok(b) => b,
        Err(e) => {
            let why =
                format!("not a command: {e} (expected {{\"command\": \"pause\", \"viewer\": N}})");
            hub.refuse(&from, &what, &why);
            return refused(StatusCode::BAD_REQUEST, &why);
        }
    };
    let mut words: Vec<&str> = SupervisorCommand::ALL.iter().map(|c| c.as_str()).collect();
    if hub.answers_interventions {
        words.extend(["done", "failed"]);
    }
    let Some(word) = words.iter().copied().find(|w| *w == body.command) else {
        let why = format!("unknown command (one of {})", words.join(", "));
        hub.refuse(&from, &what, &why);
        return refused(StatusCode::BAD_REQUEST, &why);
    };
    let from = match body.viewer {
        Some(v) => format!("console viewer {v} ({peer})"),
        None => from,
    };
    if hub.replay.is_some() {
        return refused(StatusCode::CONFLICT, "a recorded run takes no commands");
    }
    {
        let state = hub.lock();
        if state.ended {
            return refused(StatusCode::CONFLICT, "the run has ended");
        }
        // An e-stop is never refused to a viewer with the token.
        if word != "e-stop" && (body.viewer.is_none() || state.control != body.viewer) {
            let why = match state.control {
                Some(c) => format!("viewer {c} is in control; take control first"),
                None => "no viewer is in control; take control first".to_string(),
            };
            drop(state);
            hub.refuse(&from, &what, &why);
            return refused(StatusCode::CONFLICT, &why);
        }
    }
    if hub
        .commands
        .lock()
        .unwrap_or_else(PoisonError::into_inner)
        .send((word.to_string(), from))
        .is_err()
    {
        return refused(StatusCode::CONFLICT, "the run has ended");
    }
    (StatusCode::OK, axum::Json(json!({ "sent": word }))).into_response()
}

#[derive(Deserialize, Default)]
struct ControlBody {
    #[serde(default)]
    viewer: Option<u64>,
}

/// `POST /api/control {"viewer": 3}`: that viewer (or a new one, for a client with no
/// stream) takes control from whoever had it.
async fn control(
    State(hub): State<Arc<Hub>>,
    ConnectInfo(peer): ConnectInfo<SocketAddr>,
    headers: HeaderMap,
    body: axum::body::Bytes,
) -> Response {
    let from = format!("console {peer}");
    if let Err(r) = guard(&hub, &headers, &from, "take control") {
        return *r;
    }
    let body: ControlBody = if body.is_empty() {
        ControlBody::default()
    } else {
        match serde_json::from_slice(&body) {
            Ok(b) => b,
            Err(e) => return refused(StatusCode::BAD_REQUEST, &format!("not a viewer: {e}")),
        }
    };
    let viewer = {
        let mut state = hub.lock();
        let v = body.viewer.unwrap_or_else(|| {
            state.next_viewer += 1;
            state.next_viewer
        });
        state.control = Some(v);
        v
    };
    hub.bump();
    (StatusCode::OK, axum::Json(json!({ "control": viewer }))).into_response()
}

/// A viewer's ask for the next frame (`{"type": "frame"}`; when playing a recording, at
/// `t_s` on its timeline).
#[derive(Deserialize)]
struct FrameAsk {
    #[serde(rename = "type")]
    kind: String,
    #[serde(default)]
    t_s: Option<f64>,
}

#[derive(Deserialize)]
struct Hello {
    token: String,
}

/// `GET /api/stream`: a WebSocket; the first message must be `{"token": "..."}`.
async fn stream(
    State(hub): State<Arc<Hub>>,
    ConnectInfo(peer): ConnectInfo<SocketAddr>,
    headers: HeaderMap,
    ws: Result<WebSocketUpgrade, axum::extract::ws::rejection::WebSocketUpgradeRejection>,
) -> Response {
    let from = format!("console {peer}");
    // Checked first, whatever else the request gets wrong.
    if let Some(why) = hub.check_origin(&headers) {
        hub.refuse(&from, "watch", &why);
        return refused(StatusCode::FORBIDDEN, &why);
    }
    match ws {
        Ok(ws) => ws.on_upgrade(move |socket| viewer(hub, socket, from)),
        Err(e) => e.into_response(),
    }
}

async fn viewer(hub: Arc<Hub>, mut socket: WebSocket, from: String) {
    let hello = tokio::time::timeout(TOKEN_WAIT, socket.recv()).await;
    let token = match hello {
        Ok(Some(Ok(Message::Text(t)))) => serde_json::from_str::<Hello>(&t).ok().map(|h| h.token),
        _ => None,
    };
    if !token.as_deref().is_some_and(|t| hub.token_ok(t)) {
        let why = if token.is_some() {
            "wrong token"
        } else {
            "no token"
        };
        hub.refuse(&from, "watch", why);
        let _ = socket
            .send(Message::Text(
                json!({ "type": "refused", "why": why }).to_string().into(),
            ))
            .await;
        return;
    }
    let id = {
        let mut state = hub.lock();
        state.next_viewer += 1;
        state.viewers += 1;
        state.next_viewer
    };
    let _ = serve_viewer(&hub, &mut socket, id).await;
    hub.lock().viewers -= 1;
}

/// Send the plan, then every record and control change as they come, until the run ends or
/// the viewer goes.
async fn serve_viewer(hub: &Arc<Hub>, socket: &mut WebSocket, id: u64) -> Result<(), axum::Error> {
    let cameras = hub.camera.load(std::sync::atomic::Ordering::Relaxed);
    let hello = json!({
        "type": "hello",
        "viewer": id,
        "plan": hub.plan,
        "camera": cameras,
        "replay": hub.replay,
        "answers_interventions": hub.answers_interventions,
    });
    socket.send(Message::Text(hello.to_string().into())).await?;
    let mut changed = hub.changed.subscribe();
    // The control last said (`None`: not yet said).
    let (mut sent, mut control, mut diagram_sent) = (0usize, None::<Option<u64>>, false);
    // The frame being made for this viewer, if any.
    let mut making: Option<tokio::task::JoinHandle<Option<Frame>>> = None;
    loop {
        changed.borrow_and_update();
        let (batch, now_control, ended) = {
            let state = hub.lock();
            let batch: Vec<Arc<str>> = state.events[sent..].iter().take(512).cloned().collect();
            (batch, state.control, state.ended)
        };
        if !diagram_sent {
            if let Some(d) = hub.diagram.get() {
                let msg = json!({ "type": "diagram", "edges": d });
                socket.send(Message::Text(msg.to_string().into())).await?;
                diagram_sent = true;
            }
        }
        if control != Some(now_control) {
            control = Some(now_control);
            let msg = json!({ "type": "control", "viewer": now_control });
            socket.send(Message::Text(msg.to_string().into())).await?;
        }
        if !batch.is_empty() {
            sent += batch.len();
            // The records are JSON already: joined, not parsed again.
            let joined: Vec<&str> = batch.iter().map(|s| &**s).collect();
            let msg = format!("{{\"type\":\"events\",\"events\":[{}]}}", joined.join(","));
            socket.send(Message::Text(msg.into())).await?;
            continue;
        }
        if ended {
            socket
                .send(Message::Text(json!({ "type": "ended" }).to_string().into()))
                .await?;
            let _ = socket.send(Message::Close(None)).await;
            return Ok(());
        }
        tokio::select! {
            r = changed.changed() => if r.is_err() { return Ok(()) },
            m = socket.recv() => match m {
                None | Some(Err(_)) | Some(Ok(Message::Close(_))) => return Ok(()),
                // The page asks for the next frame once it has drawn the last: one in flight.
                Some(Ok(Message::Text(t))) if making.is_none() => {
                    if let Ok(ask) = serde_json::from_str::<FrameAsk>(&t) {
                        if ask.kind == "frame" {
                            making = Some(tokio::task::spawn_blocking({
                                let hub = Arc::clone(hub);
                                move || match ask.t_s {
                                    Some(t) if hub.replay.is_some() => {
                                        recorded_frame(&hub.recorded_frames, &hub.recorded_drawings, t)
                                    }
                                    _ => make_frame(&hub),
                                }
                            }));
                        }
                    }
                }
                Some(Ok(_)) => {}
            },
            made = async { making.as_mut().expect("guarded").await }, if making.is_some() => {
                making = None;
                match made.ok().flatten() {
                    Some(f) => {
                        let head = json!({ "type": "frame", "overlay": f.overlay });
                        socket.send(Message::Text(head.to_string().into())).await?;
                        socket.send(Message::Binary(f.jpeg.into())).await?;
                    }
                    None => {
                        let none = json!({ "type": "no-frame" });
                        socket.send(Message::Text(none.to_string().into())).await?;
                    }
                }
            },
        }
    }
}

/// The last needle estimate the run's estimator gave, for the overlay.
pub type LastEstimate = Arc<Mutex<Option<stitch_perception::NeedleEstimate>>>;

/// The rig's estimator, telling `last` of every estimate it gives (and nothing else
/// changed).
struct Watched {
    inner: Box<dyn stitch_perception::NeedleEstimator>,
    last: LastEstimate,
}

impl stitch_perception::NeedleEstimator for Watched {
    fn estimate_needle(
        &mut self,
    ) -> Result<stitch_perception::NeedleEstimate, stitch_perception::PerceptionError> {
        let r = self.inner.estimate_needle();
        self.note(&r);
        r
    }

    fn estimate_needle_with(
        &mut self,
        hint: Option<&stitch_perception::NeedleHint>,
    ) -> Result<stitch_perception::NeedleEstimate, stitch_perception::PerceptionError> {
        let r = self.inner.estimate_needle_with(hint);
        self.note(&r);
        r
    }

    fn trace_thread(
        &mut self,
        hint: &stitch_perception::ThreadHint,
    ) -> Result<stitch_perception::ThreadTrace, stitch_perception::PerceptionError> {
        self.inner.trace_thread(hint)
    }
}

impl Watched {
    fn note(
        &self,
        r: &Result<stitch_perception::NeedleEstimate, stitch_perception::PerceptionError>,
    ) {
        if let Ok(e) = r {
            *self.last.lock().unwrap_or_else(PoisonError::into_inner) = Some(*e);
        }
    }
}

/// What the console needs to show the mock's camera: set before the run, used by it.
pub struct MockView {
    hub: Arc<Hub>,
    camera: stitch_sim::CameraConfig,
}

impl Console {
    /// The mock's camera for this console, drawn as `camera` (the mock's `[camera]`) sees.
    pub fn mock_view(&self, camera: stitch_sim::CameraConfig) -> MockView {
        self.hub
            .camera
            .store(true, std::sync::atomic::Ordering::Relaxed);
        MockView {
            hub: Arc::clone(&self.hub),
            camera,
        }
    }
}

impl MockView {
    /// Show `world` through the camera at half its resolution, with the estimates of the
    /// rig's estimator and the jaws drawn over it. Gives what watches the rig's estimator.
    pub fn show(self, world: &stitch_sim::MockDvrk) -> anyhow::Result<Watch> {
        use rand_chacha::rand_core::SeedableRng;
        let half = stitch_sim::CameraConfig {
            width: self.camera.width / 2,
            height: self.camera.height / 2,
            focal_px: self.camera.focal_px / 2.0,
            blur_px: self.camera.blur_px / 2.0,
            ..self.camera.clone()
        };
        let renderer = stitch_sim::StereoRenderer::new(half, world.phantom_view())
            .map_err(|e| anyhow::anyhow!("the console's camera: {e}"))?;
        let last: LastEstimate = Arc::new(Mutex::new(None));
        let needle = world.needle_model();
        let watched = Arc::clone(&last);
        let (world, clock) = (world.clone(), world.clock().clone());
        // Its own generator for the image noise: the run's streams are never drawn from.
        let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(0xc0_5013);
        let source: FrameSource = Box::new(move || {
            use stitch_robot::Clock;
            let scene = world.peek_scene_view();
            let pair = renderer.render(&scene, &stitch_robot::Pose::identity(), &mut rng);
            let draw = Drawn {
                calibration: renderer.calibration(),
                scale: 1.0,
            };
            let now = clock.now();
            let estimate = *last.lock().unwrap_or_else(PoisonError::into_inner);
            let (arc, confidence, age) = match &estimate {
                Some(e) => (
                    draw.needle(&needle, &e.pose),
                    Some(e.confidence),
                    Some(now.saturating_sub(e.stamp).as_secs_f64()),
                ),
                None => (Vec::new(), None, None),
            };
            let jaws: Vec<Value> = scene
                .tools
                .iter()
                .zip(["PSM1", "PSM2"])
                .filter_map(|(t, arm)| {
                    let mut jaw = draw.jaw(arm, &t.pose)?;
                    jaw["jaw_rad"] = json!(t.jaw_rad);
                    Some(jaw)
                })
                .collect();
            Some(Frame {
                jpeg: jpeg(&pair.left.data, pair.left.width, pair.left.height)?,
                overlay: json!({
                    "t_s": now.as_secs_f64(),
                    "width": pair.left.width,
                    "height": pair.left.height,
                    "needle": (!arc.is_empty()).then_some(arc),
                    "confidence": confidence,
                    "estimate_age_s": age,
                    "jaws": jaws,
                }),
            })
        });
        *self
            .hub
            .frames
            .lock()
            .unwrap_or_else(PoisonError::into_inner) = Some(source);
        Ok(Watch { last: watched })
    }
}

/// Watches a rig's needle estimator for the console's overlay.
pub struct Watch {
    last: LastEstimate,
}

impl Watch {
    /// `rig` with its estimator watched (its estimates unchanged).
    pub fn rig(self, rig: stitch_primitives::Rig) -> stitch_primitives::Rig {
        stitch_primitives::Rig {
            estimator: Box::new(Watched {
                inner: rig.estimator,
                last: self.last,
            }),
            ..rig
        }
    }
}

/// The last left image a streamed camera gave (over ROS 2), kept only while a viewer waits
/// for one: nothing is copied on the engine's thread otherwise.
#[derive(Default)]
struct Latest {
    wanted: std::sync::atomic::AtomicBool,
    frame: Mutex<
        Option<(
            Duration,
            stitch_robot::RgbImage,
            stitch_robot::StereoCalibration,
        )>,
    >,
    ready: std::sync::Condvar,
}

/// The console's view of a streamed stereo camera (`--robot ros2 --perception pipeline`):
/// the left image of each pair the pipeline captures, with the last estimate drawn over it.
#[cfg_attr(not(feature = "ros2"), allow(dead_code))] // the camera is streamed over ROS 2
pub struct CameraView {
    latest: Arc<Latest>,
    last: LastEstimate,
    /// The arms (PSM1, PSM2) whose measured poses the overlay draws, once the rig is known.
    arms: Arms,
}

/// Arms to draw, read on the console's thread (their measured poses only).
type Arms = Arc<Mutex<Vec<Arc<dyn stitch_robot::Arm>>>>;

impl Console {
    /// Show the camera the run's pipeline captures from, for a needle of this model.
    pub fn camera_view(&self, needle: stitch_robot::Needle) -> CameraView {
        self.hub
            .camera
            .store(true, std::sync::atomic::Ordering::Relaxed);
        let latest = Arc::new(Latest::default());
        let last: LastEstimate = Arc::new(Mutex::new(None));
        let arms: Arms = Arc::new(Mutex::new(Vec::new()));
        let (l, e, a) = (Arc::clone(&latest), Arc::clone(&last), Arc::clone(&arms));
        let source: FrameSource = Box::new(move || {
            l.wanted.store(true, std::sync::atomic::Ordering::Relaxed);
            let mut slot = l.frame.lock().unwrap_or_else(PoisonError::into_inner);
            if slot.is_none() {
                slot = l
                    .ready
                    .wait_timeout(slot, Duration::from_secs(1))
                    .unwrap_or_else(PoisonError::into_inner)
                    .0;
            }
            let (stamp, left, calibration) = slot.take()?;
            drop(slot);
            let full = image::RgbImage::from_raw(left.width, left.height, left.data)?;
            let half = image::imageops::thumbnail(&full, left.width / 2, left.height / 2);
            let estimate = *e.lock().unwrap_or_else(PoisonError::into_inner);
            let draw = Drawn {
                calibration: &calibration,
                scale: 0.5,
            };
            let arc = estimate
                .map(|est| draw.needle(&needle, &est.pose))
                .unwrap_or_default();
            let arms = a.lock().unwrap_or_else(PoisonError::into_inner).clone();
            let jaws: Vec<Value> = arms
                .iter()
                .filter_map(|arm| draw.jaw(arm.name(), &arm.measured_cp().ok()?))
                .collect();
            Some(Frame {
                jpeg: jpeg(half.as_raw(), half.width(), half.height())?,
                overlay: json!({
                    "t_s": stamp.as_secs_f64(),
                    "width": half.width(),
                    "height": half.height(),
                    "needle": (!arc.is_empty()).then_some(arc),
                    "confidence": estimate.map(|e| e.confidence),
                    "estimate_age_s": estimate.map(|e| stamp.saturating_sub(e.stamp).as_secs_f64()),
                    "jaws": jaws,
                }),
            })
        });
        *self
            .hub
            .frames
            .lock()
            .unwrap_or_else(PoisonError::into_inner) = Some(source);
        CameraView { latest, last, arms }
    }
}

#[cfg_attr(not(feature = "ros2"), allow(dead_code))]
impl CameraView {
    /// The camera's observer: `inner` (the recorder's, if any), and a copy of the left image
    /// for the console when a viewer waits for one.
    pub fn observer(
        &self,
        inner: Option<stitch_robot::FrameObserver>,
    ) -> stitch_robot::FrameObserver {
        let latest = Arc::clone(&self.latest);
        Arc::new(move |frame, calibration| {
            if let Some(inner) = &inner {
                inner(frame, calibration);
            }
            if latest
                .wanted
                .swap(false, std::sync::atomic::Ordering::Relaxed)
            {
                *latest.frame.lock().unwrap_or_else(PoisonError::into_inner) =
                    Some((frame.stamp, frame.left.clone(), calibration.clone()));
                latest.ready.notify_all();
            }
        })
    }

    /// `rig` with its estimator watched for the overlay, and its arms' measured poses drawn
    /// (give it the rig before a recorder's tap: the console's reads are not the run's).
    pub fn rig(&self, rig: stitch_primitives::Rig) -> stitch_primitives::Rig {
        *self.arms.lock().unwrap_or_else(PoisonError::into_inner) =
            vec![Arc::clone(&rig.right), Arc::clone(&rig.left)];
        Watch {
            last: Arc::clone(&self.last),
        }
        .rig(rig)
    }
}

/// What the page draws over a left image shown `scale` times the calibrated size: pixels
/// to 0.1 px, points behind the camera left out.
struct Drawn<'a> {
    calibration: &'a stitch_robot::StereoCalibration,
    scale: f64,
}

impl Drawn<'_> {
    fn px(&self, p: &stitch_robot::Point) -> Option<[f64; 2]> {
        let [u, v] = self.calibration.left_pixel(p)?;
        let round = |x: f64| (x * self.scale * 10.0).round() / 10.0;
        Some([round(u), round(v)])
    }

    /// The needle's half circle at `pose`, tip first.
    fn needle(&self, needle: &stitch_robot::Needle, pose: &stitch_robot::Pose) -> Vec<[f64; 2]> {
        (0..=24)
            .map(|i| needle.point_at(std::f64::consts::PI * f64::from(i) / 24.0))
            .filter_map(|p| self.px(&(pose * p)))
            .collect()
    }

    /// A tool at `pose`: its tip and a point 1 cm back along its blades.
    fn jaw(&self, arm: &str, pose: &stitch_robot::Pose) -> Option<Value> {
        let tip = self.px(&(pose * stitch_robot::Point::origin()))?;
        let back = self.px(&(pose * stitch_robot::Point::new(0.0, 0.0, -0.01)))?;
        Some(json!({ "arm": arm, "tip": tip, "back": back }))
    }
}

/// An RGB image as JPEG (quality 80).
fn jpeg(rgb: &[u8], width: u32, height: u32) -> Option<Vec<u8>> {
    let mut out = Vec::new();
    image::codecs::jpeg::JpegEncoder::new_with_quality(&mut out, 80)
        .encode(rgb, width, height, image::ExtendedColorType::Rgb8)
        .ok()?;
    Some(out)
}

#[cfg(test)]
mod tests {
    use super::*;
    use std::io::{Read, Write};

    fn plan() -> Arc<Plan> {
        let spec = stitch_robot::WoundSpec::default();
        let wound = stitch_robot::Wound::linear(&spec).expect("wound");
        let loader = stitch_engine::PlanLoader::new(&wound, stitch_engine::ScriptLimits::default());
        let path = std::path::Path::new(env!("CARGO_MANIFEST_DIR")).join("../scripts/stitch.rhai");
        Arc::new(stitch_engine::load_plan(&loader, &path).expect("plan").plan)
    }

    /// POST `body` to `path` with the token; the status and the body.
    fn post(console: &Console, path: &str, body: &str) -> (u16, String) {
        let mut s = std::net::TcpStream::connect(console.addr).expect("connect");
        let req = format!(
            "POST {path} HTTP/1.1\r\nHost: {}\r\nAuthorization: Bearer {}\r\nConnection: close\r\n\
             Content-Length: {}\r\n\r\n{body}",
            console.addr,
            console.hub.token,
            body.len()
        );
        s.write_all(req.as_bytes()).expect("send");
        let mut out = String::new();
        let _ = s.read_to_string(&mut out);
        let status = out
            .split(' ')
            .nth(1)
            .and_then(|c| c.parse().ok())
            .unwrap_or(0);
        (
            status,
            out.split_once("\r\n\r\n")
                .map_or("", |(_, b)| b)
                .to_string(),
        )
    }

    #[test]
    fn done_and_failed_reach_the_supervisor_only_where_the_console_answers_interventions() {
        let addr: SocketAddr = "127.0.0.1:0".parse().expect("addr");
        for person in [true, false] {
            let (console, feeds) = Console::start(addr, false, &plan(), person).expect("start");
            let (got, body) = post(&console, "/api/control", "");
            assert_eq!(got, 200, "{body}");
            let viewer: Value = serde_json::from_str(&body).expect("json");
            let viewer = viewer["control"].as_u64().expect("viewer");
            for word in ["done", "failed", "pause"] {
                let (got, body) = post(
                    &console,
                    "/api/command",
                    &format!(r#"{{"command":"{word}","viewer":{viewer}}}"#),
                );
                if person || word == "pause" {
                    assert_eq!(got, 200, "{word}: {body}");
                    let (heard, from) = feeds
                        .commands
                        .recv_timeout(Duration::from_secs(5))
                        .expect("heard");
                    assert_eq!(heard, word);
                    assert!(
                        from.starts_with(&format!("console viewer {viewer} (")),
                        "{from}"
                    );
                } else {
                    assert_eq!(got, 400, "{word} on the mock: {body}");
                    let r = feeds.refusals.try_recv().expect("journaled");
                    assert_eq!(r.command, word);
                }
            }
        }
    }
}
