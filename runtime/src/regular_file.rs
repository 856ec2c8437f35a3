//! Opening the files of a dataset: regular files only, without blocking.
//!
//! A FIFO would block the opening thread until some writer comes, `/dev/zero` or a socket would
//! be read without end: a run on a dataset that holds one must fail that item, not hang. So the
//! file is opened with `O_NONBLOCK` (which changes nothing for a regular file and makes opening a
//! FIFO return at once) and its type checked on the opened descriptor, with no race against a
//! rename between a check and an open. A symbolic link to a regular file is followed.

use anyhow::{bail, Result};
use std::fs::{File, Metadata};
use std::os::unix::fs::{FileTypeExt, OpenOptionsExt};
use std::path::Path;

/// `path` opened for reading, with its metadata, if it is a regular file. The errors do not name
/// the path: callers say what the file is and where.
pub fn open(path: &Path) -> Result<(File, Metadata)> {
    let file = std::fs::OpenOptions::new().read(true).custom_flags(libc::O_NONBLOCK).open(path)?;
    let meta = file.metadata()?;
    if !meta.is_file() {
        bail!("it is not a regular file but {}; dist4d reads only regular files", kind(&meta));
    }
    Ok((file, meta))
}

/// What a file that is not regular is, for messages.
fn kind(meta: &Metadata) -> &'static str {
    let t = meta.file_type();
    if t.is_dir() {
        "a folder"
    } else if t.is_fifo() {
        "a FIFO"
    } else if t.is_char_device() {
        "a character device"
    } else if t.is_block_device() {
        "a block device"
    } else if t.is_socket() {
        "a socket"
    } else {
        "a special file"
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn only_regular_files_open_and_a_fifo_does_not_block() {
        let dir = tempfile::tempdir().unwrap();
        let f = dir.path().join("f");
        std::fs::write(&f, b"bytes").unwrap();
        assert_eq!(open(&f).unwrap().1.len(), 5);
        let link = dir.path().join("link");
        std::os::unix::fs::symlink(&f, &link).unwrap();
        assert!(open(&link).is_ok(), "a link to a regular file is followed");
        let fifo = dir.path().join("fifo");
        assert!(std::process::Command::new("mkfifo").arg(&fifo).status().unwrap().success());
        let e = open(&fifo).unwrap_err().to_string();
        assert!(e.contains("not a regular file but a FIFO"), "{e}");
        let e = open(Path::new("/dev/zero")).unwrap_err().to_string();
        assert!(e.contains("a character device"), "{e}");
        assert!(open(dir.path()).unwrap_err().to_string().contains("a folder"));
    }
}
