//! The live view as a Foxglove client sees it: a WebSocket client with the `foxglove.sdk.v1`
//! subprotocol connects, checks the advertised channels against the schemas of an MCAP log of the
//! same messages, subscribes, and parses a message of every schema. Then `flownav sim --live`
//! and the errors of `--live`.

use std::collections::{BTreeMap, BTreeSet};
use std::io::{BufRead, BufReader};
use std::net::{SocketAddr, TcpListener, TcpStream};
use std::process::{Command, Stdio};
use std::time::{Duration, Instant};

use base64::Engine as _;
use flownav::logging::sample::{self, SampleImages};
use flownav::logging::{LiveImages, LiveServer, LogOptions, LogWriter};
use hal::Calibration;
use serde_json::{Value, json};
use tungstenite::client::IntoClientRequest;
use tungstenite::{Message, WebSocket};

/// Longest any step waits: a guard against a hang, far above what a loaded machine needs.
const GUARD: Duration = Duration::from_secs(60);

type Socket = WebSocket<TcpStream>;

/// A client of the live view: connects with the subprotocol, subscribes to every channel as it
/// is advertised, and keeps the messages received per channel.
struct Viewer {
    ws: Socket,
    /// Advertised channels by id: topic, schema name, and the whole advertisement.
    channels: BTreeMap<u64, Value>,
    /// Subscription id → channel id.
    subscriptions: BTreeMap<u32, u64>,
    /// Messages received: channel id → (log time, payload).
    received: BTreeMap<u64, Vec<(u64, Vec<u8>)>>,
}

impl Viewer {
    fn connect(addr: SocketAddr) -> Self {
        let mut request = format!("ws://{addr}").into_client_request().unwrap();
        request.headers_mut().insert("Sec-WebSocket-Protocol", "foxglove.sdk.v1".parse().unwrap());
        let stream = TcpStream::connect(addr).unwrap();
        let (ws, response) = tungstenite::client(request, stream).unwrap();
        assert_eq!(response.headers()["sec-websocket-protocol"], "foxglove.sdk.v1");
        ws.get_ref().set_read_timeout(Some(Duration::from_millis(20))).unwrap();
        Self { ws, channels: BTreeMap::new(), subscriptions: BTreeMap::new(), received: BTreeMap::new() }
    }

    /// Reads what has arrived (up to a short read timeout), subscribing to new channels.
    fn poll(&mut self) {
        loop {
            let msg = match self.ws.read() {
                Ok(m) => m,
                Err(tungstenite::Error::Io(e))
                    if matches!(e.kind(), std::io::ErrorKind::WouldBlock | std::io::ErrorKind::TimedOut) =>
                {
                    return;
                }
                Err(e) => panic!("live view connection: {e}"),
            };
            match msg {
                Message::Text(text) => {
                    let v: Value = serde_json::from_str(text.as_str()).unwrap();
                    if v["op"] == "advertise" {
                        let mut subs = Vec::new();
                        for ch in v["channels"].as_array().unwrap() {
                            let id = ch["id"].as_u64().unwrap();
                            let sub = self.subscriptions.len() as u32 + 1;
                            self.subscriptions.insert(sub, id);
                            self.channels.insert(id, ch.clone());
                            subs.push(json!({"id": sub, "channelId": id}));
                        }
                        let req = json!({"op": "subscribe", "subscriptions": subs});
                        self.ws.send(Message::text(req.to_string())).unwrap();
                    }
                }
                Message::Binary(data) => {
                    // Message data: opcode 1, subscription id (u32 LE), log time (u64 LE), payload.
                    assert!(data.len() >= 13, "short binary message");
                    if data[0] != 1 {
                        continue;
                    }
                    let sub = u32::from_le_bytes(data[1..5].try_into().unwrap());
                    let log_time = u64::from_le_bytes(data[5..13].try_into().unwrap());
                    let channel = self.subscriptions[&sub];
                    self.received.entry(channel).or_default().push((log_time, data[13..].to_vec()));
                }
                _ => {}
            }
        }
    }

    /// `topic schema` of every channel that delivered at least one message.
    fn seen(&self) -> BTreeSet<String> {
        self.received.keys().map(|id| self.key(*id)).collect()
    }

    fn key(&self, id: u64) -> String {
        let ch = &self.channels[&id];
        format!("{} {}", ch["topic"].as_str().unwrap(), ch["schemaName"].as_str().unwrap())
    }
}

/// The schemas of an MCAP sample log, as `topic schema` → schema text.
fn mcap_schemas(path: &std::path::Path) -> BTreeMap<String, String> {
    let bytes = std::fs::read(path).unwrap();
    let mut out = BTreeMap::new();
    for m in mcap::MessageStream::new(&bytes).unwrap() {
        let m = m.unwrap();
        let schema = m.channel.schema.as_ref().unwrap();
        assert_eq!((m.channel.message_encoding.as_str(), schema.encoding.as_str()), ("json", "jsonschema"));
        let text = String::from_utf8(schema.data.to_vec()).unwrap();
        out.insert(format!("{} {}", m.channel.topic, schema.name), text);
    }
    out
}

#[test]
fn a_foxglove_client_gets_every_logged_channel_with_the_mcap_schemas() {
    let (w, h) = (64, 48);
    let calibration = Calibration::nominal_c310().scaled_to(w as u32, h as u32);
    // The same messages to an MCAP file: its channels are what the live view must advertise.
    let dir = tempfile::tempdir().unwrap();
    let mcap_path = dir.path().join("sample.mcap");
    sample::write_sample(&mcap_path, 12, SampleImages::Mono8, LogOptions::new("test")).unwrap();
    let mut expected = mcap_schemas(&mcap_path);
    // The file's own statistics (written at flushes) are not a topic of the live view.
    expected.retain(|k, _| !k.starts_with("/logger/stats"));

    let server = LiveServer::start("127.0.0.1:0".parse().unwrap(), LiveImages::Mono8).unwrap();
    assert_ne!(server.addr().port(), 0);
    let mut options = LogOptions::new("test");
    options.live = Some(server.sink());
    let writer = LogWriter::live_only(options).unwrap();
    // Logged before anyone connects: the live view keeps these for later viewers.
    writer.calibration(0, &calibration);
    writer.world(0, &sample::world());

    let mut viewer = Viewer::connect(server.addr());
    let start = Instant::now();
    let mut i = 0;
    while viewer.seen() != expected.keys().cloned().collect() {
        assert!(
            start.elapsed() < GUARD,
            "channels with a message: {:?}, expected {:?}",
            viewer.seen(),
            expected.keys()
        );
        // Frame by frame, as a run logs them (status and log lines every 10th frame).
        sample::log_frame(&writer, i, SampleImages::Mono8, w, h);
        i += 1;
        std::thread::sleep(Duration::from_millis(5));
        viewer.poll();
    }

    for (id, ch) in &viewer.channels {
        let key = viewer.key(*id);
        assert_eq!(ch["encoding"], "json", "{key}");
        assert_eq!(ch["schemaEncoding"], "jsonschema", "{key}");
        // Channels are advertised up front; those the sample logs must carry the file's schema.
        if let Some(schema) = expected.get(&key) {
            assert_eq!(ch["schema"].as_str(), Some(schema.as_str()), "{key}: schema differs from the MCAP's");
        }
    }
    for (id, messages) in &viewer.received {
        let key = viewer.key(*id);
        let schema: Value = serde_json::from_str(viewer.channels[id]["schema"].as_str().unwrap()).unwrap();
        for (_, payload) in messages {
            let msg: Value = serde_json::from_slice(payload).unwrap_or_else(|e| panic!("{key}: not JSON: {e}"));
            for field in schema["required"].as_array().into_iter().flatten() {
                assert!(msg.get(field.as_str().unwrap()).is_some(), "{key}: no {field} in {msg}");
            }
        }
    }
    let by_topic = |topic: &str| {
        let id = viewer.channels.iter().find(|(_, c)| c["topic"] == topic).map(|(id, _)| *id).unwrap();
        &viewer.received[&id]
    };
    // The image, decoded: mono8 pixels of the sample frame its log time names.
    let (t, payload) = &by_topic("/camera/image")[0];
    let img: Value = serde_json::from_slice(payload).unwrap();
    assert_eq!(
        (img["width"].as_u64(), img["height"].as_u64(), img["encoding"].as_str()),
        (Some(64), Some(48), Some("mono8"))
    );
    let pixels = base64::engine::general_purpose::STANDARD.decode(img["data"].as_str().unwrap()).unwrap();
    assert_eq!(pixels, sample::frame(t / sample::FRAME_NS, w, h).data());
    // The calibration was logged before the client connected and still arrived, unchanged.
    let (t, payload) = &by_topic("/camera/calibration")[0];
    let cal: Value = serde_json::from_slice(payload).unwrap();
    assert_eq!((*t, cal["width"].as_u64(), cal["K"][0].as_f64()), (0, Some(64), Some(calibration.camera.fx)));
    // Set-points carry their frame's log time.
    let (t, payload) = &by_topic("/control/setpoint")[0];
    let sp: Value = serde_json::from_slice(payload).unwrap();
    assert_eq!(sp, serde_json::to_value(sample::setpoint(t / sample::FRAME_NS)).unwrap());

    drop(viewer);
    writer.close().unwrap();
    let stats = server.close();
    assert!(stats.sent >= expected.len() as u64 && stats.clients == 1, "{stats:?}");
    assert_eq!(stats.dropped, 0, "a 5 ms frame interval must not fill the live view's queue");
}

fn flownav() -> Command {
    let mut cmd = Command::new(env!("CARGO_BIN_EXE_flownav"));
    cmd.args(["--flow-backend", "cpu"]);
    cmd
}

#[test]
fn sim_live_serves_the_camera_while_it_drives() {
    let mut child = flownav()
        .args([
            "sim",
            "--live",
            "127.0.0.1:0",
            "--no-log",
            "--quiet",
            "--max-time",
            "30",
            "--fps",
            "10",
            "--size",
            "320x180",
        ])
        .stdout(Stdio::null())
        .stderr(Stdio::piped())
        .spawn()
        .unwrap();
    let mut stderr = BufReader::new(child.stderr.take().unwrap());
    let mut line = String::new();
    let addr: SocketAddr = loop {
        line.clear();
        if stderr.read_line(&mut line).unwrap() == 0 {
            let _ = child.kill();
            panic!("flownav sim exited without a 'live view on' line");
        }
        if let Some(rest) = line.trim().strip_prefix("live view on ws://") {
            break rest.split_whitespace().next().unwrap().parse().unwrap();
        }
    };
    let mut viewer = Viewer::connect(addr);
    let start = Instant::now();
    let wanted =
        ["/camera/image foxglove.RawImage", "/tf foxglove.FrameTransform", "/control/setpoint flownav.Setpoint"];
    while !wanted.iter().all(|k| viewer.seen().contains(*k)) {
        if start.elapsed() > GUARD || child.try_wait().unwrap().is_some() {
            let _ = child.kill();
            panic!("channels with a message: {:?}", viewer.seen());
        }
        viewer.poll();
    }
    let _ = child.kill();
    let _ = child.wait();
}

#[test]
fn live_errors_name_the_option_and_the_fix() {
    let taken = TcpListener::bind("127.0.0.1:0").unwrap();
    let port = taken.local_addr().unwrap().port();
    let out = flownav().args(["sim", "--live", &format!("127.0.0.1:{port}"), "--no-log"]).output().unwrap();
    let err = String::from_utf8_lossy(&out.stderr);
    assert!(!out.status.success());
    assert!(err.contains(&format!("--live 127.0.0.1:{port}")) && err.contains("already in use"), "{err}");

    let out = flownav().args(["sim", "--live", "robot:8765"]).output().unwrap();
    let err = String::from_utf8_lossy(&out.stderr);
    assert!(!out.status.success());
    assert!(err.contains("--live") && err.contains("0.0.0.0:8765"), "{err}");

    // `run` checks the live view before it opens the base: the error is the live view's even
    // though the base's port does not exist.
    let dir = tempfile::tempdir().unwrap();
    for i in 0..2 {
        flownav::frames::save_png(&sample::frame(i, 320, 240), dir.path().join(format!("{i:04}.png"))).unwrap();
    }
    let out = flownav()
        .arg("--calib")
        .arg(concat!(env!("CARGO_MANIFEST_DIR"), "/calib/c310.toml"))
        .args(["run", "--no-log", "--base", "fnp:/nonexistent/tty-flownav", "--live", &format!("127.0.0.1:{port}")])
        .arg("--camera")
        .arg(format!("frames:{}", dir.path().display()))
        .output()
        .unwrap();
    let err = String::from_utf8_lossy(&out.stderr);
    assert!(!out.status.success());
    assert!(err.contains("already in use") && !err.contains("tty-flownav"), "{err}");
    drop(taken);
}

/// The shipped layout opens panels on topics flownav logs, with fields its schemas have.
#[test]
fn the_foxglove_layout_names_logged_topics() {
    let text =
        std::fs::read_to_string(concat!(env!("CARGO_MANIFEST_DIR"), "/docs/foxglove/flownav-layout.json")).unwrap();
    let layout: Value = serde_json::from_str(&text).unwrap();
    let dir = tempfile::tempdir().unwrap();
    let path = dir.path().join("s.mcap");
    sample::write_sample(&path, 2, SampleImages::Mono8, LogOptions::new("test")).unwrap();
    let schemas: BTreeMap<String, Value> = mcap_schemas(&path)
        .into_iter()
        .map(|(k, s)| (k.split_once(' ').unwrap().0.to_string(), serde_json::from_str(&s).unwrap()))
        .collect();
    // A message path `/topic.a.b` must name a property chain of the topic's JSON schema.
    let check_path = |p: &str| {
        let (topic, fields) = p.split_once('.').unwrap_or((p, ""));
        let mut schema =
            schemas.get(topic).unwrap_or_else(|| panic!("layout names {topic}, which flownav does not log"));
        for f in fields.split('.').filter(|f| !f.is_empty()) {
            schema = schema["properties"].get(f).unwrap_or_else(|| panic!("layout path {p}: no field {f}"));
        }
    };
    let mut paths = Vec::new();
    for (id, config) in layout["configById"].as_object().unwrap() {
        match id.split('!').next().unwrap() {
            "Plot" | "StateTransitions" => {
                paths.extend(config["paths"].as_array().unwrap().iter().map(|p| p["value"].as_str().unwrap()))
            }
            "RawMessages" => paths.push(config["topicPath"].as_str().unwrap()),
            "Image" => {
                let m = &config["imageMode"];
                paths.extend([m["imageTopic"].as_str().unwrap(), m["calibrationTopic"].as_str().unwrap()]);
                paths.extend(m["annotations"].as_object().unwrap().keys().map(String::as_str));
            }
            "3D" => paths.extend(config["topics"].as_object().unwrap().keys().map(String::as_str)),
            _ => {}
        }
    }
    assert!(paths.len() >= 10, "{paths:?}");
    for p in paths {
        check_path(p);
    }
}
