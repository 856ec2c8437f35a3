//! Writes to a worker's stdin that give up at a deadline. A pipe holds 64 KiB: once a worker
//! stops reading (stuck in its model, or never reading at all) a blocking write of a large
//! request, or of the pings and cancels that pile up, would hold the engine past every deadline.
//! So the pipe is made non-blocking and each write waits in `poll(2)` for at most what is left.

use std::io::{self, Write};
use std::os::fd::AsRawFd;
use std::time::Instant;

/// Makes writes to `pipe` return `WouldBlock` instead of waiting.
pub fn set_nonblocking(pipe: &impl AsRawFd) -> io::Result<()> {
    let fd = pipe.as_raw_fd();
    // SAFETY: fcntl(2) on a descriptor we own, reading then setting its status flags.
    let flags = unsafe { libc::fcntl(fd, libc::F_GETFL) };
    if flags < 0 || unsafe { libc::fcntl(fd, libc::F_SETFL, flags | libc::O_NONBLOCK) } < 0 {
        return Err(io::Error::last_os_error());
    }
    Ok(())
}

/// Writes all of `bytes` to the non-blocking `pipe` before `deadline`, or fails with
/// `TimedOut` (what was written by then is written: the caller gives the worker up).
pub fn write_all_by<W: Write + AsRawFd>(pipe: &mut W, mut bytes: &[u8], deadline: Instant) -> io::Result<()> {
    while !bytes.is_empty() {
        match pipe.write(bytes) {
            Ok(0) => return Err(io::ErrorKind::WriteZero.into()),
            Ok(n) => bytes = &bytes[n..],
            Err(e) if e.kind() == io::ErrorKind::Interrupted => {}
            Err(e) if e.kind() == io::ErrorKind::WouldBlock => {
                let left = deadline.saturating_duration_since(Instant::now());
                if left.is_zero() {
                    return Err(io::Error::new(io::ErrorKind::TimedOut, "the worker does not read its stdin"));
                }
                let mut fd = libc::pollfd { fd: pipe.as_raw_fd(), events: libc::POLLOUT, revents: 0 };
                // Rounded up: a wait of 0 ms would spin until the deadline.
                let ms = left.as_millis().saturating_add(1).min(i32::MAX as u128) as i32;
                // SAFETY: poll(2) on one pollfd that lives across the call. Its result is not
                // needed: the next write says whether there is room, an error or a closed pipe.
                unsafe { libc::poll(&mut fd, 1, ms) };
            }
            Err(e) => return Err(e),
        }
    }
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;
    use std::time::Duration;

    #[test]
    fn a_write_to_a_pipe_nobody_reads_gives_up_at_the_deadline() {
        let mut child =
            std::process::Command::new("sleep").arg("30").stdin(std::process::Stdio::piped()).spawn().unwrap();
        let mut stdin = child.stdin.take().unwrap();
        set_nonblocking(&stdin).unwrap();
        let t = Instant::now();
        let err = write_all_by(&mut stdin, &vec![b'x'; 1 << 20], t + Duration::from_millis(200)).unwrap_err();
        assert_eq!(err.kind(), io::ErrorKind::TimedOut);
        assert!(t.elapsed() < Duration::from_secs(2), "{:?}", t.elapsed());
        let _ = child.kill();
        let _ = child.wait();
    }
}
