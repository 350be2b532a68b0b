//! Pseudo-terminals for the simulated bases: a raw-mode pty whose slave path (`/dev/pts/N`) a
//! driver opens like a serial port, while the simulator reads and writes the master.
//!
//! The simulator holds no slave descriptor, so the master tells whether a driver has the port
//! open ([`Pty::peer_open`]): while none has, the master reports a hang-up and its reads fail
//! (the raw mode stays set for the next open). Closing a [`Pty`] (dropping it) hangs up the
//! slave side: that is how a disconnect is simulated. An optional stable symlink
//! ([`Pty::link_at`]) lets a driver reopen "the same port" after the simulator made a new pty,
//! like a udev symlink for a USB adapter that was unplugged and plugged back in.

use nix::fcntl::{FcntlArg, OFlag, fcntl};
use nix::sys::termios::{SetArg, cfmakeraw, tcgetattr, tcsetattr};
use std::fs::File;
use std::io::{self, Read, Write};
use std::os::fd::AsFd;
use std::path::{Path, PathBuf};
use std::pin::Pin;
use std::sync::Arc;
use std::sync::atomic::{AtomicU64, Ordering};
use std::task::{Context, Poll, ready};
use tokio::io::Interest;
use tokio::io::unix::AsyncFd;
use tokio::io::{AsyncRead, AsyncWrite, ReadBuf};

/// A pty opened in raw mode: the master as an async byte stream, the slave's path for drivers.
pub struct Pty {
    master: AsyncFd<File>,
    path: PathBuf,
    /// Bytes written to the master that the kernel refused because nobody is reading the slave.
    unread_dropped: Arc<AtomicU64>,
    /// `read` calls made on the master (each a system call), successful or not.
    read_calls: Arc<AtomicU64>,
}

impl Pty {
    /// Opens a new pty (inside a tokio runtime). The slave is raw 8-bit: no echo, no line editing.
    pub fn open() -> io::Result<Self> {
        let pair = nix::pty::openpty(None, None).map_err(io::Error::from)?;
        let mut t = tcgetattr(&pair.slave).map_err(io::Error::from)?;
        cfmakeraw(&mut t);
        tcsetattr(&pair.slave, SetArg::TCSANOW, &t).map_err(io::Error::from)?;
        let path = nix::unistd::ttyname(&pair.slave).map_err(io::Error::from)?;
        let flags = OFlag::from_bits_truncate(fcntl(&pair.master, FcntlArg::F_GETFL).map_err(io::Error::from)?);
        fcntl(&pair.master, FcntlArg::F_SETFL(flags | OFlag::O_NONBLOCK)).map_err(io::Error::from)?;
        let master = File::from(pair.master);
        let master = register(master)?;
        // `pair.slave` closes here: the driver's open is the only one.
        Ok(Self { master, path, unread_dropped: Arc::new(AtomicU64::new(0)), read_calls: Arc::new(AtomicU64::new(0)) })
    }

    /// Whether some process has the slave (the port) open now: the master reports a hang-up
    /// while none has.
    pub fn peer_open(&self) -> bool {
        use nix::poll::{PollFd, PollFlags, PollTimeout, poll};
        let mut fds = [PollFd::new(self.master.get_ref().as_fd(), PollFlags::POLLIN)];
        match poll(&mut fds, PollTimeout::ZERO) {
            Ok(_) => !fds[0].revents().is_some_and(|r| r.contains(PollFlags::POLLHUP)),
            Err(_) => false,
        }
    }

    /// The slave's path (`/dev/pts/N`), to be opened by a driver.
    pub fn path(&self) -> &Path {
        &self.path
    }

    /// Points the symlink `link` at this pty's slave (replacing it atomically).
    pub fn link_at(&self, link: &Path) -> io::Result<()> {
        let tmp = link.with_extension("flownav-tmp");
        let _ = std::fs::remove_file(&tmp);
        std::os::unix::fs::symlink(&self.path, &tmp)?;
        std::fs::rename(&tmp, link)
    }

    /// Bytes dropped because the slave's input buffer was full (nobody reading the port).
    pub fn unread_dropped(&self) -> u64 {
        self.unread_dropped.load(Ordering::Relaxed)
    }

    /// `read` system calls made on the master so far (what an idle or hung-up port costs).
    pub fn read_calls(&self) -> u64 {
        self.read_calls.load(Ordering::Relaxed)
    }

    /// Registers the master with the reactor afresh (a duplicate descriptor of the same open
    /// file), dropping the old registration and its readiness state. Epoll reports the
    /// master's state at registration, so nothing that is pending is lost.
    fn reregister(&mut self) -> io::Result<()> {
        let fresh = register(self.master.get_ref().try_clone()?)?;
        // The old registration is removed and its descriptor closed here.
        self.master = fresh;
        Ok(())
    }
}

/// Registers the master with the reactor for reading only: writes never wait (see
/// [`Pty::poll_write`]), so write readiness would only wake the reactor for nothing.
fn register(master: File) -> io::Result<AsyncFd<File>> {
    // SAFETY: the AsyncFd owns the file, so the descriptor stays open (and is not reused)
    // until the AsyncFd is dropped, which deregisters it first.
    unsafe { AsyncFd::register_with_interest(master, Interest::READABLE) }.map_err(|e| e.into_parts().1)
}

impl AsyncRead for Pty {
    fn poll_read(self: Pin<&mut Self>, cx: &mut Context<'_>, buf: &mut ReadBuf<'_>) -> Poll<io::Result<()>> {
        let this = self.get_mut();
        loop {
            let mut guard = ready!(this.master.poll_read_ready(cx))?;
            let stale_hangup = guard.ready().is_read_closed();
            let unfilled = buf.initialize_unfilled();
            let read_calls = &this.read_calls;
            match guard.try_io(|f| {
                read_calls.fetch_add(1, Ordering::Relaxed);
                f.get_ref().read(unfilled)
            }) {
                Ok(Ok(n)) => {
                    buf.advance(n);
                    return Poll::Ready(Ok(()));
                }
                Ok(Err(e)) => return Poll::Ready(Err(e)),
                // The master reported a hang-up (no driver had the port open) and a driver has
                // opened it since: the read would block, so the hang-up is over. Tokio keeps a
                // reported hang-up for good (it never clears "read closed"), so waiting on this
                // registration again would report "ready" at once, every time, and this loop
                // would spin in `read` until the driver sends a byte (tokio's task budget only
                // makes it yield every 128 tries and run again at once). A fresh registration
                // starts with the state epoll reports now.
                Err(_would_block) if stale_hangup => this.reregister()?,
                Err(_would_block) => continue,
            }
        }
    }
}

impl AsyncWrite for Pty {
    /// Like a UART transmitter, never waits for the other side: when the slave's buffer is full
    /// (no driver reading), the bytes are dropped and counted.
    fn poll_write(self: Pin<&mut Self>, _cx: &mut Context<'_>, buf: &[u8]) -> Poll<io::Result<usize>> {
        match self.master.get_ref().write(buf) {
            Err(e) if e.kind() == io::ErrorKind::WouldBlock => {
                self.unread_dropped.fetch_add(buf.len() as u64, Ordering::Relaxed);
                Poll::Ready(Ok(buf.len()))
            }
            r => Poll::Ready(r),
        }
    }

    fn poll_flush(self: Pin<&mut Self>, _cx: &mut Context<'_>) -> Poll<io::Result<()>> {
        Poll::Ready(Ok(()))
    }

    fn poll_shutdown(self: Pin<&mut Self>, _cx: &mut Context<'_>) -> Poll<io::Result<()>> {
        Poll::Ready(Ok(()))
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use tokio::io::{AsyncReadExt, AsyncWriteExt};

    #[tokio::test]
    async fn bytes_cross_both_ways_binary_safe() {
        let mut pty = Pty::open().unwrap();
        assert!(pty.path().starts_with("/dev/pts"), "{:?}", pty.path());
        let mut port = std::fs::OpenOptions::new().read(true).write(true).open(pty.path()).unwrap();
        let all: Vec<u8> = (0..=255u8).collect();
        pty.write_all(&all).await.unwrap();
        let mut got = vec![0u8; 256];
        port.read_exact(&mut got).unwrap();
        assert_eq!(got, all);
        port.write_all(&all).unwrap();
        let mut got = vec![0u8; 256];
        pty.read_exact(&mut got).await.unwrap();
        assert_eq!(got, all);
    }

    #[tokio::test]
    async fn tells_whether_a_driver_has_the_port_open() {
        let pty = Pty::open().unwrap();
        assert!(!pty.peer_open(), "nobody has opened the slave yet");
        let port = std::fs::OpenOptions::new().read(true).write(true).open(pty.path()).unwrap();
        assert!(pty.peer_open());
        drop(port);
        assert!(!pty.peer_open(), "the driver closed the port");
        let _again = std::fs::OpenOptions::new().read(true).write(true).open(pty.path()).unwrap();
        assert!(pty.peer_open(), "reopened");
    }

    /// Polls one read of the idle port exactly once; returns the outcome and the `read` calls it
    /// made. Should that poll keep retrying the read, a byte from the driver (after 1000 tries)
    /// ends it, so the test fails instead of hanging.
    fn poll_once_idle(pty: &mut Pty, port: std::fs::File) -> (Poll<io::Result<usize>>, u64, std::fs::File) {
        use std::sync::atomic::AtomicBool;
        let calls = pty.read_calls.clone();
        let before = calls.load(Ordering::Relaxed);
        let done = Arc::new(AtomicBool::new(false));
        let watcher = {
            let done = done.clone();
            std::thread::spawn(move || {
                let mut port = port;
                while !done.load(Ordering::Relaxed) {
                    if calls.load(Ordering::Relaxed) - before > 1000 {
                        port.write_all(b"!").unwrap();
                        break;
                    }
                    std::thread::sleep(std::time::Duration::from_millis(1));
                }
                port
            })
        };
        let mut bytes = [0u8; 16];
        let mut buf = ReadBuf::new(&mut bytes);
        let waker = std::task::Waker::noop();
        let polled = Pin::new(&mut *pty).poll_read(&mut Context::from_waker(waker), &mut buf);
        let polled = polled.map_ok(|()| buf.filled().len());
        done.store(true, Ordering::Relaxed);
        let port = watcher.join().unwrap();
        (polled, pty.read_calls() - before, port)
    }

    /// The master reports a hang-up while no driver has the port open; once a driver has opened
    /// it, waiting for bytes on the idle port must wait, not retry `read`, and still see every
    /// byte. Again after the driver hangs up and reconnects.
    #[tokio::test]
    async fn an_idle_port_costs_no_reads_after_a_hang_up() {
        let mut pty = Pty::open().unwrap();
        let mut buf = [0u8; 16];
        for round in 0..2 {
            // The reactor sees the hang-up: the read is tried and fails.
            let e = pty.read(&mut buf).await.unwrap_err();
            assert_eq!(e.raw_os_error(), Some(nix::errno::Errno::EIO as i32), "round {round}: {e}");
            let port = std::fs::OpenOptions::new().read(true).write(true).open(pty.path()).unwrap();
            let (polled, reads, mut port) = poll_once_idle(&mut pty, port);
            assert!(polled.is_pending(), "round {round}: the idle port gave {polled:?} after {reads} reads");
            assert_eq!(reads, 1, "round {round}: one read finds the hang-up over");
            port.write_all(&[0xA5, 0x00, 0xFF]).unwrap();
            let mut got = [0u8; 3];
            pty.read_exact(&mut got).await.unwrap();
            assert_eq!(got, [0xA5, 0x00, 0xFF], "round {round}");
            let (polled, reads, port) = poll_once_idle(&mut pty, port);
            assert!(polled.is_pending() && reads <= 1, "round {round}: {polled:?} after {reads} reads");
            drop(port);
        }
    }
}
