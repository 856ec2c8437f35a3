//! Lines from a worker's pipes, read with a bound: a worker that writes a line without end (a
//! model printing an array, a runaway loop) must not make the engine buffer all of it. `lines()`
//! would: it keeps reading until a newline comes.

use std::io::{self, BufRead};

/// How a bounded read of one line ended.
#[derive(Debug, PartialEq, Eq)]
pub enum End {
    /// At a newline (consumed, not kept).
    Newline,
    /// At the end of the stream (a last line without a newline is kept).
    Eof,
    /// After `max` bytes and no newline: the rest of the line is left in the reader.
    TooLong,
}

/// Appends the next line's bytes to `buf`, which holds at most `max` bytes when this returns: a
/// line of exactly `max` bytes is whole, a longer one is [`End::TooLong`].
pub fn read_line(r: &mut impl BufRead, buf: &mut Vec<u8>, max: usize) -> io::Result<End> {
    loop {
        let chunk = fill(r)?;
        if chunk.is_empty() {
            return Ok(End::Eof);
        }
        let room = max.saturating_sub(buf.len());
        if let Some(n) = chunk.iter().position(|&b| b == b'\n').filter(|&n| n <= room) {
            buf.extend_from_slice(&chunk[..n]);
            r.consume(n + 1);
            return Ok(End::Newline);
        }
        if room == 0 {
            return Ok(End::TooLong);
        }
        let take = chunk.len().min(room);
        buf.extend_from_slice(&chunk[..take]);
        r.consume(take);
    }
}

/// The reader's buffered bytes, filled if empty (retried when interrupted); empty at the end.
fn fill(r: &mut impl BufRead) -> io::Result<&[u8]> {
    loop {
        match r.fill_buf() {
            Err(e) if e.kind() == io::ErrorKind::Interrupted => continue,
            // Asked again: the borrow checker refuses returning the first answer from inside the
            // loop; a filled buffer comes back without another read.
            Ok(_) => return r.fill_buf(),
            Err(e) => return Err(e),
        }
    }
}

/// Reads past the rest of the current line (its newline included) keeping none of it: the
/// number of bytes skipped, and whether the stream ended first.
pub fn skip_line(r: &mut impl BufRead) -> io::Result<(u64, End)> {
    let mut skipped = 0u64;
    loop {
        let chunk = fill(r)?;
        if chunk.is_empty() {
            return Ok((skipped, End::Eof));
        }
        if let Some(n) = chunk.iter().position(|&b| b == b'\n') {
            r.consume(n + 1);
            return Ok((skipped + n as u64, End::Newline));
        }
        let n = chunk.len();
        r.consume(n);
        skipped += n as u64;
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use std::io::BufReader;

    /// Every line of `text` read with bound `max` through a 4-byte buffer (so lines span reads).
    fn all(text: &str, max: usize) -> Vec<(String, End)> {
        let mut r = BufReader::with_capacity(4, text.as_bytes());
        let mut out = Vec::new();
        loop {
            let mut buf = Vec::new();
            let end = read_line(&mut r, &mut buf, max).unwrap();
            let stop = end == End::Eof;
            if end == End::TooLong {
                skip_line(&mut r).unwrap();
            }
            out.push((String::from_utf8(buf).unwrap(), end));
            if stop {
                return out;
            }
        }
    }

    #[test]
    fn lines_up_to_the_bound_are_whole_and_longer_ones_stop_at_it() {
        use End::*;
        assert_eq!(
            all("ab\nabcdef\nabcdefg\n\nxy", 6),
            [("ab", Newline), ("abcdef", Newline), ("abcdef", TooLong), ("", Newline), ("xy", Eof)]
                .map(|(s, e)| (s.to_string(), e))
        );
        assert_eq!(all("", 6), [(String::new(), Eof)]);
    }

    #[test]
    fn a_line_without_end_is_read_no_further_than_the_bound() {
        let endless = std::io::repeat(b'x');
        let mut r = BufReader::new(endless);
        let mut buf = Vec::new();
        assert_eq!(read_line(&mut r, &mut buf, 1 << 20).unwrap(), End::TooLong);
        assert_eq!(buf.len(), 1 << 20);
    }

    #[test]
    fn skipping_a_line_counts_it_and_stops_after_its_newline() {
        let mut r = BufReader::with_capacity(4, &b"0123456789\nnext"[..]);
        assert_eq!(skip_line(&mut r).unwrap(), (10, End::Newline));
        let mut buf = Vec::new();
        assert_eq!((read_line(&mut r, &mut buf, 10).unwrap(), buf), (End::Eof, b"next".to_vec()));
    }
}
