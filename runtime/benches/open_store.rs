//! Opening a store that many writers appended to: every cluster shard (and every run) writes
//! segments of its own, so a store shared by a cluster collects thousands of segment files.
//!
//!   cargo bench -p dist4d-runtime --bench open_store              # 10,000 segments x 100 records
//!   cargo bench -p dist4d-runtime --bench open_store -- 2000 50   # SEGMENTS RECORDS_PER_SEGMENT
//!
//! Prints the time to open the store (listing, mapping and indexing every segment; the page
//! cache is warm, as on a node that just wrote them), to look up every key, and to refresh (what
//! a run does when it takes over an item another process finished), against the same records in
//! one segment (what `gc` compacts them into).

use dist4d_runtime::digest::Digest;
use dist4d_runtime::item::ItemKey;
use dist4d_runtime::record::{OutputRef, TaskRecord};
use dist4d_runtime::segment::SegmentWriter;
use dist4d_runtime::store::{Access, Store};
use std::path::Path;
use std::time::Instant;

fn record(i: u64) -> TaskRecord {
    TaskRecord {
        key: Digest::of(&i.to_le_bytes()),
        stage: "complete".into(),
        item: ItemKey::new(&[(i / 240) as u32, (i / 6 % 40) as u32, (i % 6) as u32]),
        kind: "CompleteDepth".into(),
        version: 3,
        params: Digest::of(b"(max_depth:100.0)"),
        inputs: vec![],
        outputs: vec![OutputRef { digest: Digest::of(&(i + 1).to_le_bytes()), size: 5_760_000, inline: None }],
        finished_ms: 1_795_000_000_000 + i,
        micros: 1_000,
    }
}

fn write(root: &Path, segments: u64, per: u64) {
    let ac = root.join("ac");
    for s in 0..segments {
        let mut w = SegmentWriter::create(&ac, &format!("writer-{s:06}")).unwrap();
        for r in 0..per {
            w.append(&record(s * per + r).encode()).unwrap();
        }
        w.flush().unwrap();
    }
}

fn measure(root: &Path, n: u64) -> (f64, f64, f64) {
    let t = Instant::now();
    let store = Store::open(root, Access::Shared).unwrap();
    let open = t.elapsed().as_secs_f64();
    assert_eq!(store.record_count() as u64, n);
    let t = Instant::now();
    for i in 0..n {
        assert!(store.lookup(&Digest::of(&i.to_le_bytes())).is_some());
    }
    let lookup = t.elapsed().as_secs_f64() / n as f64;
    let t = Instant::now();
    assert_eq!(store.refresh().unwrap(), 0);
    (open, lookup, t.elapsed().as_secs_f64())
}

fn main() {
    let args: Vec<u64> = std::env::args().skip(1).filter_map(|a| a.parse().ok()).collect();
    let (segments, per) = (args.first().copied().unwrap_or(10_000), args.get(1).copied().unwrap_or(100));
    let n = segments * per;
    let many = tempfile::tempdir().unwrap();
    let t = Instant::now();
    write(many.path(), segments, per);
    println!("wrote {segments} segments x {per} records in {:.1}s", t.elapsed().as_secs_f64());
    let one = tempfile::tempdir().unwrap();
    write(one.path(), 1, n);
    for (name, dir) in [("many segments", many.path()), ("one segment", one.path())] {
        measure(dir, n); // warm the page cache, as after writing
        let (open, lookup, refresh) = measure(dir, n);
        println!(
            "{name:>14}: open {:.0} ms ({:.2} us/record), lookup {:.2} us, refresh (nothing new) {:.1} ms",
            open * 1e3,
            open * 1e6 / n as f64,
            lookup * 1e6,
            refresh * 1e3
        );
    }
}
