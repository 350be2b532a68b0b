//! The live view: the logged topics served over the Foxglove WebSocket protocol (the `foxglove`
//! crate's server), so Foxglove shows the robot while it drives.
//!
//! The log writer's thread hands every message it writes (already encoded: the same topics, JSON
//! encoding and JSON schemas as the MCAP file) to a [`LiveSink`]; a thread of the live view
//! passes them to the server, which queues them per client. The sink's queue is bounded in
//! messages and bytes and never waits: when the live view falls behind, the message is dropped and
//! counted ([`LiveStats::dropped`]). The control path never sees the live view at all, only the
//! log writer's own non-blocking queues. Without a client connected nothing is copied.
//!
//! Messages the writer repeats at the start of every split part (calibration, camera mount,
//! world) are kept and sent again whenever a client subscribes, so a viewer that connects
//! mid-run still gets the camera model, the `/tf` mount and the world.

use std::collections::HashMap;
use std::net::SocketAddr;
use std::sync::atomic::{AtomicBool, AtomicU64, AtomicUsize, Ordering};
use std::sync::{Arc, Mutex};
use std::thread::JoinHandle;
use std::time::Duration;

use crossbeam_channel::{Receiver, RecvTimeoutError, Sender, TrySendError};
use foxglove::websocket::{ChannelView, Client, ServerListener};
use foxglove::{Context, PartialMetadata, RawChannel, Schema, WebSocketServer, WebSocketServerHandle};
use serde::Serialize;

use super::{SCHEMA_ENCODING, Topic};

/// Where `--live` serves when given without an address: this machine only.
pub const DEFAULT_ADDR: &str = "127.0.0.1:8765";

/// Messages waiting for the live thread at most.
const QUEUE_MESSAGES: usize = 512;
/// Bytes waiting for the live thread at most (a 640×480 mono8 frame is ~0.4 MB in JSON).
const QUEUE_BYTES: usize = 16 << 20;
/// Messages each client's queue in the server holds before the oldest are dropped (the crate's
/// default is 1024; a few seconds of every topic at 30 fps, without holding hundreds of frames).
const CLIENT_BACKLOG: usize = 512;

/// How the run's camera images are logged, so the live view can advertise `/camera/image` with
/// its schema before any viewer connects.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum LiveImages {
    /// `foxglove.RawImage` mono8 (the simulator, frame folders, cameras without MJPEG).
    Mono8,
    /// `foxglove.CompressedImage` JPEG (an MJPEG camera).
    Jpeg,
}

/// Why the live view could not start.
#[derive(Debug, thiserror::Error)]
pub enum LiveError {
    #[error(
        "--live {addr}: the address is already in use (another flownav, or a Foxglove bridge?); stop it or pick another port, e.g. --live {suggest}"
    )]
    InUse { addr: SocketAddr, suggest: SocketAddr },
    #[error(
        "--live {addr}: cannot listen there: {error} (use an address of this machine, e.g. --live 127.0.0.1:8765, or --live 0.0.0.0:8765 for every interface)"
    )]
    Bind { addr: SocketAddr, error: std::io::Error },
    #[error("--live {addr}: cannot start the Foxglove WebSocket server: {message}")]
    Start { addr: SocketAddr, message: String },
}

/// Parses `--live`'s `HOST:PORT` (an IP address and a port), with an error that says what to pass.
pub fn parse_addr(s: &str) -> Result<SocketAddr, String> {
    s.trim().parse::<SocketAddr>().map_err(|_| {
        format!(
            "{s:?} is not an IP:PORT address; pass e.g. 127.0.0.1:8765 (this machine only) or 0.0.0.0:8765 (every interface, to watch from another computer)"
        )
    })
}

/// What the live view sent and dropped.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, Serialize)]
pub struct LiveStats {
    /// Messages handed to the WebSocket server (while at least one client was connected).
    pub sent: u64,
    /// Messages dropped because the live view's queue was full (it fell behind).
    pub dropped: u64,
    /// Clients that connected during the run.
    pub clients: u64,
}

struct Shared {
    pending_bytes: AtomicUsize,
    dropped: AtomicU64,
    sent: AtomicU64,
    clients_now: AtomicUsize,
    clients_total: AtomicU64,
    /// Set by a subscription or a new latched message: the live thread (re)sends the latched ones.
    resend: AtomicBool,
    stop: AtomicBool,
    latched: Mutex<Vec<Message>>,
}

#[derive(Clone)]
struct Message {
    topic: Topic,
    log_time_ns: u64,
    data: Vec<u8>,
}

/// The log writer's side of the live view: cheap to clone, never blocks.
#[derive(Clone)]
pub struct LiveSink {
    tx: Sender<Message>,
    shared: Arc<Shared>,
}

impl std::fmt::Debug for LiveSink {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("LiveSink").field("stats", &self.stats()).finish_non_exhaustive()
    }
}

impl LiveSink {
    /// Offers one encoded message. `latched` messages (calibration, camera mount, world) are kept
    /// and sent to every client that subscribes later. Returns whether it was queued.
    pub(crate) fn offer(&self, topic: Topic, log_time_ns: u64, data: &[u8], latched: bool) -> bool {
        if latched {
            if let Ok(mut kept) = self.shared.latched.lock() {
                kept.retain(|m| m.topic != topic);
                kept.push(Message { topic, log_time_ns, data: data.to_vec() });
            }
            self.shared.resend.store(true, Ordering::Release);
            return true;
        }
        if !self.has_clients() {
            return false;
        }
        let waiting = self.shared.pending_bytes.fetch_add(data.len(), Ordering::AcqRel);
        if waiting + data.len() > QUEUE_BYTES {
            return self.refuse(data.len());
        }
        match self.tx.try_send(Message { topic, log_time_ns, data: data.to_vec() }) {
            Ok(()) => true,
            Err(TrySendError::Full(_) | TrySendError::Disconnected(_)) => self.refuse(data.len()),
        }
    }

    fn refuse(&self, len: usize) -> bool {
        self.shared.pending_bytes.fetch_sub(len, Ordering::AcqRel);
        self.shared.dropped.fetch_add(1, Ordering::Relaxed);
        false
    }

    /// Whether a viewer is connected (without one, messages are not even copied).
    pub fn has_clients(&self) -> bool {
        self.shared.clients_now.load(Ordering::Acquire) > 0
    }

    /// Sent and dropped so far.
    pub fn stats(&self) -> LiveStats {
        LiveStats {
            sent: self.shared.sent.load(Ordering::Relaxed),
            dropped: self.shared.dropped.load(Ordering::Relaxed),
            clients: self.shared.clients_total.load(Ordering::Relaxed),
        }
    }
}

/// Keeps the client count and asks for the latched messages again on every subscription.
struct Listener(Arc<Shared>);

impl ServerListener for Listener {
    fn on_subscribe(&self, _client: Client, _channel: ChannelView) {
        self.0.resend.store(true, Ordering::Release);
    }

    fn on_client_connect(&self) {
        self.0.clients_now.fetch_add(1, Ordering::AcqRel);
        self.0.clients_total.fetch_add(1, Ordering::Relaxed);
    }

    fn on_client_disconnect(&self) {
        // Saturating: a disconnect is never reported without its connect, but a wrap would
        // make the sink copy everything for nobody.
        let _ = self.0.clients_now.fetch_update(Ordering::AcqRel, Ordering::Acquire, |n| n.checked_sub(1));
    }
}

/// The running server: a WebSocket listener on its own single-thread runtime, and the thread
/// that feeds it from the [`LiveSink`]. [`LiveServer::close`] (or dropping it) stops both.
pub struct LiveServer {
    sink: LiveSink,
    addr: SocketAddr,
    server: Option<WebSocketServerHandle>,
    thread: Option<JoinHandle<()>>,
    runtime: Option<tokio::runtime::Runtime>,
}

impl LiveServer {
    /// Starts serving on `addr` (port 0: any free port, see [`LiveServer::addr`]). Fails before
    /// anything else starts when the address cannot be bound.
    ///
    /// Every channel is created here, before a viewer can connect: the crate's server (0.30)
    /// sends a new channel's advertisement before it records the channel for the client, so a
    /// viewer that subscribes at once to a channel added while it is connected can be refused
    /// ("unknown channel"). Channels that exist when a viewer connects are recorded first.
    pub fn start(addr: SocketAddr, images: LiveImages) -> Result<Self, LiveError> {
        let start_err = |message: String| LiveError::Start { addr, message };
        // Its own runtime, so sending images to a viewer never competes with the base's serial
        // link on the run's runtime.
        let runtime = tokio::runtime::Builder::new_multi_thread()
            .worker_threads(1)
            .thread_name("flownav-live-ws")
            .enable_all()
            .build()
            .map_err(|e| start_err(format!("cannot start its runtime: {e}")))?;
        let shared = Arc::new(Shared {
            pending_bytes: AtomicUsize::new(0),
            dropped: AtomicU64::new(0),
            sent: AtomicU64::new(0),
            clients_now: AtomicUsize::new(0),
            clients_total: AtomicU64::new(0),
            resend: AtomicBool::new(false),
            stop: AtomicBool::new(false),
            latched: Mutex::new(Vec::new()),
        });
        let context = Context::new();
        let server = runtime
            .block_on(
                WebSocketServer::new()
                    .name("flownav")
                    .bind(addr.ip().to_string(), addr.port())
                    .context(&context)
                    .message_backlog_size(CLIENT_BACKLOG)
                    .listener(Arc::new(Listener(Arc::clone(&shared))))
                    .start(),
            )
            .map_err(|e| match e {
                foxglove::FoxgloveError::Bind(error) if error.kind() == std::io::ErrorKind::AddrInUse => {
                    LiveError::InUse { addr, suggest: SocketAddr::new(addr.ip(), addr.port().wrapping_add(1).max(1)) }
                }
                foxglove::FoxgloveError::Bind(error) => LiveError::Bind { addr, error },
                other => start_err(other.to_string()),
            })?;
        let bound = SocketAddr::new(addr.ip(), server.port());
        let (tx, rx) = crossbeam_channel::bounded(QUEUE_MESSAGES);
        let mut feeder = Feeder { context, channels: HashMap::new(), shared: Arc::clone(&shared) };
        let image = match images {
            LiveImages::Mono8 => Topic::ImageRaw,
            LiveImages::Jpeg => Topic::ImageCompressed,
        };
        for topic in Topic::ALL.into_iter().filter(|t| !matches!(t, Topic::ImageRaw | Topic::ImageCompressed)) {
            feeder.channel(topic);
        }
        feeder.channel(image);
        let thread = std::thread::Builder::new()
            .name("flownav-live".into())
            .spawn(move || feeder.run(rx))
            .map_err(|e| start_err(format!("cannot start its thread: {e}")))?;
        Ok(Self {
            sink: LiveSink { tx, shared },
            addr: bound,
            server: Some(server),
            thread: Some(thread),
            runtime: Some(runtime),
        })
    }

    /// The address served, with the real port when started on port 0.
    pub fn addr(&self) -> SocketAddr {
        self.addr
    }

    /// The `ws://` URL to open in Foxglove.
    pub fn url(&self) -> String {
        format!("ws://{}", self.addr)
    }

    /// A sink for the log writer ([`super::LogOptions::live`]).
    pub fn sink(&self) -> LiveSink {
        self.sink.clone()
    }

    /// Stops the server (clients are disconnected) and reports what was sent and dropped.
    pub fn close(mut self) -> LiveStats {
        self.shutdown();
        self.sink.stats()
    }

    fn shutdown(&mut self) {
        self.sink.shared.stop.store(true, Ordering::Release);
        if let Some(thread) = self.thread.take() {
            let _ = thread.join();
        }
        if let Some(server) = self.server.take() {
            // Dropping the shutdown handle aborts the client tasks at once; the run is over.
            drop(server.stop());
        }
        if let Some(runtime) = self.runtime.take() {
            runtime.shutdown_timeout(Duration::from_millis(200));
        }
    }
}

impl Drop for LiveServer {
    fn drop(&mut self) {
        self.shutdown();
    }
}

/// The live thread: creates a channel per topic and schema on first use (as the MCAP writer
/// registers them) and logs each message with its log time.
struct Feeder {
    context: Arc<Context>,
    channels: HashMap<(&'static str, &'static str), Arc<RawChannel>>,
    shared: Arc<Shared>,
}

impl Feeder {
    fn run(mut self, rx: Receiver<Message>) {
        loop {
            if self.shared.resend.swap(false, Ordering::AcqRel) {
                let latched = self.shared.latched.lock().map(|k| k.clone()).unwrap_or_default();
                for m in &latched {
                    self.publish(m);
                }
            }
            match rx.recv_timeout(Duration::from_millis(50)) {
                Ok(m) => {
                    self.shared.pending_bytes.fetch_sub(m.data.len(), Ordering::AcqRel);
                    self.publish(&m);
                }
                Err(RecvTimeoutError::Timeout) => {}
                Err(RecvTimeoutError::Disconnected) => break,
            }
            if self.shared.stop.load(Ordering::Acquire) {
                break;
            }
        }
    }

    /// The channel of `topic`, created on first use with the JSON schema exactly as the MCAP
    /// writer registers it.
    fn channel(&mut self, topic: Topic) -> Option<Arc<RawChannel>> {
        let key = (topic.name(), topic.schema_name());
        if let Some(c) = self.channels.get(&key) {
            return Some(Arc::clone(c));
        }
        let schema = serde_json::to_vec(&topic.schema()).unwrap_or_default();
        let built = self
            .context
            .channel_builder(topic.name())
            .message_encoding("json")
            .schema(Schema::new(topic.schema_name(), SCHEMA_ENCODING, schema))
            .build_raw();
        match built {
            Ok(c) => Some(Arc::clone(self.channels.entry(key).or_insert(c))),
            Err(e) => {
                tracing::warn!(topic = topic.name(), "live view: cannot add the channel: {e}");
                None
            }
        }
    }

    fn publish(&mut self, m: &Message) {
        let Some(channel) = self.channel(m.topic) else { return };
        if channel.has_sinks() {
            channel.log_with_meta(&m.data, PartialMetadata { log_time: Some(m.log_time_ns) });
            self.shared.sent.fetch_add(1, Ordering::Relaxed);
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn sink(cap: usize) -> (LiveSink, Receiver<Message>) {
        let (tx, rx) = crossbeam_channel::bounded(cap);
        let shared = Arc::new(Shared {
            pending_bytes: AtomicUsize::new(0),
            dropped: AtomicU64::new(0),
            sent: AtomicU64::new(0),
            clients_now: AtomicUsize::new(1),
            clients_total: AtomicU64::new(1),
            resend: AtomicBool::new(false),
            stop: AtomicBool::new(false),
            latched: Mutex::new(Vec::new()),
        });
        (LiveSink { tx, shared }, rx)
    }

    #[test]
    fn a_stalled_live_view_drops_and_counts_instead_of_waiting() {
        let (live, rx) = sink(3);
        let queued = (0..10).filter(|&i| live.offer(Topic::Setpoint, i, b"{}", false)).count();
        assert_eq!(queued, 3);
        assert_eq!(live.stats().dropped, 7);
        assert_eq!(rx.len(), 3);
        assert_eq!(live.shared.pending_bytes.load(Ordering::Acquire), 6);
    }

    #[test]
    fn the_byte_budget_bounds_big_messages() {
        let (live, _rx) = sink(QUEUE_MESSAGES);
        let frame = vec![b'x'; QUEUE_BYTES / 4 + 1];
        let queued = (0..8).filter(|&i| live.offer(Topic::ImageRaw, i, &frame, false)).count();
        assert_eq!((queued, live.stats().dropped), (3, 5));
    }

    #[test]
    fn nothing_is_copied_without_a_client_but_latched_messages_are_kept() {
        let (live, rx) = sink(8);
        live.shared.clients_now.store(0, Ordering::Release);
        assert!(!live.offer(Topic::Setpoint, 1, b"{}", false));
        assert!(live.offer(Topic::Calibration, 1, b"{\"a\":1}", true));
        assert!(live.offer(Topic::Calibration, 2, b"{\"a\":2}", true));
        assert!(live.offer(Topic::CameraMount, 2, b"{}", true));
        assert_eq!((rx.len(), live.stats().dropped), (0, 0));
        let kept = live.shared.latched.lock().unwrap();
        let cal: Vec<_> = kept.iter().filter(|m| m.topic == Topic::Calibration).collect();
        assert_eq!((kept.len(), cal.len(), cal[0].log_time_ns), (2, 1, 2));
        assert!(live.shared.resend.load(Ordering::Acquire));
    }

    #[test]
    fn bad_addresses_say_what_to_pass() {
        assert_eq!(parse_addr("0.0.0.0:8765").unwrap().port(), 8765);
        assert!(parse_addr("[::1]:9000").is_ok());
        let e = parse_addr("robot:8765").unwrap_err();
        assert!(e.contains("127.0.0.1:8765"), "{e}");
        assert!(parse_addr("127.0.0.1").is_err());
    }
}
