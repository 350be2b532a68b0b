//! Error kinds the runtime can act on, in the shape of embedded-hal: every driver has its own
//! error type, and each error tells its [`ErrorKind`].

/// What generic code (the runtime) needs to know about a hardware error to react to it.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash)]
pub enum ErrorKind {
    /// The device went away (unplugged, port closed, hang-up): reconnect with back-off.
    Disconnected,
    /// Nothing arrived in time (camera stall, silent base): stop the robot, keep trying.
    Timeout,
    /// Bytes or frames arrived but make no sense (corrupt JPEG, bad CRC): count, skip.
    BadData,
    /// The device cannot do what the configuration asks (format, size, rate): fix the config.
    Unsupported,
    /// Anything else (I/O errors, permissions): report it to a human.
    Other,
    /// A finite source (a frame folder played as a camera) has delivered its last frame: stop
    /// the robot and end the run normally. Live devices never report it.
    EndOfStream,
}

/// Implemented by every driver's error type.
pub trait Error: std::error::Error + Send + Sync + 'static {
    fn kind(&self) -> ErrorKind;
}
