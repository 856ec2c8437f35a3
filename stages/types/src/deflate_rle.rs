//! A zlib stream for byte planes: runs of one byte as matches at distance 1, everything else as
//! literals, one dynamic Huffman block.
//!
//! Why not a general deflate: the byte planes of a PXR24 block (the high, middle and low bytes of
//! each 24-bit float's difference from its left neighbour) have their redundancy in runs (the high
//! plane of a smooth surface is zeros) and in skewed byte frequencies, not in repeats at other
//! distances. Measured on curated 1600x900 maps (docs/BENCHMARKS.md, "Store and
//! encoders"): zlib's RLE strategy leaves them within 2% of its level-1 size and
//! of miniz_oxide's, and skipping the hash chains makes this encoder several times faster.
//! Any inflater reads the stream (zlib, miniz_oxide, OpenEXR's).

/// Longest match deflate codes.
const MAX_RUN: usize = 258;
/// Longest code of the literal/length alphabet, and of the code-length alphabet.
const MAX_BITS: u32 = 15;
const MAX_CODE_LENGTH_BITS: u32 = 7;
/// Symbols of the literal/length alphabet: 256 literals, end of block, lengths 257-285.
const SYMBOLS: usize = 286;
const END_OF_BLOCK: usize = 256;

/// First length of each length code 257-285, and its extra bits.
const LENGTH_BASE: [u16; 29] =
    [3, 4, 5, 6, 7, 8, 9, 10, 11, 13, 15, 17, 19, 23, 27, 31, 35, 43, 51, 59, 67, 83, 99, 115, 131, 163, 195, 227, 258];
const LENGTH_EXTRA: [u8; 29] = [0, 0, 0, 0, 0, 0, 0, 0, 1, 1, 1, 1, 2, 2, 2, 2, 3, 3, 3, 3, 4, 4, 4, 4, 5, 5, 5, 5, 0];
/// The order in which the code-length alphabet's lengths are sent (RFC 1951, 3.2.7).
const CODE_LENGTH_ORDER: [usize; 19] = [16, 17, 18, 0, 8, 7, 9, 6, 10, 5, 11, 4, 12, 3, 13, 2, 14, 1, 15];

/// `input` as a zlib stream (RFC 1950) of one dynamic-Huffman deflate block (RFC 1951).
pub fn zlib_rle(input: &[u8]) -> Vec<u8> {
    // Tokens: a literal byte (< 256) or 256 + a run's length (3-258), with their frequencies.
    let mut tokens = vec![0u16; input.len()];
    let mut n = 0;
    let mut freq = [0u32; SYMBOLS];
    let length_code = length_codes();
    let mut i = 0;
    while i < input.len() {
        // Most bytes of a noisy plane differ from the one before, and most pairs that do not are
        // not runs of 3: three compares decide before the run is measured.
        let b = input[i];
        let starts_run = i > 0 && i + 2 < input.len() && b == input[i - 1] && input[i + 1] == b && input[i + 2] == b;
        let run = if starts_run { run_length(input, i, b) } else { 0 };
        if run >= 3 {
            tokens[n] = 256 + run as u16;
            freq[257 + length_code[run] as usize] += 1;
            i += run;
        } else {
            tokens[n] = b as u16;
            freq[b as usize] += 1;
            i += 1;
        }
        n += 1;
    }
    tokens.truncate(n);
    freq[END_OF_BLOCK] = 1;

    let lit_lengths = huffman_lengths(&freq, MAX_BITS);
    let lit_codes = canonical_codes(&lit_lengths);
    // One distance is used (1, code 0); a second code of length 1 makes the code complete,
    // which every inflater accepts.
    let dist_lengths = [1u8, 1];
    let hlit = lit_lengths.iter().rposition(|&l| l > 0).map_or(257, |p| (p + 1).max(257));

    let mut out = BitWriter::with_capacity(2 * input.len() + 1024);
    out.bytes.extend_from_slice(&[0x78, 0x01]); // deflate, 32 KiB window, fastest
    out.put(1, 1); // the last block
    out.put(2, 2); // dynamic Huffman
    write_code_lengths(&mut out, &lit_lengths[..hlit], &dist_lengths);
    // Each token's bits, at most 15 + 5 + 1, in one entry: its code, then for a run the length's
    // extra bits and the distance code of distance 1 (code 0, one bit: 0); the bit count on top.
    let bits_of: Vec<u32> = (0..256 + MAX_RUN + 1)
        .map(|t| {
            let (code, len) = if t < 256 {
                (lit_codes[t] as u32, lit_lengths[t] as u32)
            } else if t - 256 >= 3 {
                let run = t - 256;
                let c = length_code[run] as usize;
                let s = 257 + c;
                let (code, len) = (lit_codes[s] as u32, lit_lengths[s] as u32);
                let extra = LENGTH_EXTRA[c] as u32;
                (code | ((run - LENGTH_BASE[c] as usize) as u32) << len, len + extra + 1)
            } else {
                (0, 0)
            };
            code | len << 24
        })
        .collect();
    out.put_tokens(&tokens, &bits_of);
    out.put(lit_codes[END_OF_BLOCK] as u64, lit_lengths[END_OF_BLOCK] as u32);
    let mut bytes = out.finish();
    bytes.extend_from_slice(&simd_adler32::adler32(&input).to_be_bytes());
    bytes
}

/// How many bytes from `at` on equal `byte`, up to [`MAX_RUN`]; eight at a time.
#[inline]
fn run_length(input: &[u8], at: usize, byte: u8) -> usize {
    let end = input.len().min(at + MAX_RUN);
    let pattern = u64::from_ne_bytes([byte; 8]);
    let mut i = at;
    while i + 8 <= end {
        let word = u64::from_le_bytes(input[i..i + 8].try_into().expect("8 bytes"));
        let diff = word ^ pattern;
        if diff != 0 {
            return i - at + (diff.trailing_zeros() / 8) as usize;
        }
        i += 8;
    }
    while i < end && input[i] == byte {
        i += 1;
    }
    i - at
}

/// The length code (0-28, symbol 257 + it) of each run length 0-258 (entries below 3 unused).
fn length_codes() -> [u8; MAX_RUN + 1] {
    let mut t = [0u8; MAX_RUN + 1];
    for (c, &base) in LENGTH_BASE.iter().enumerate() {
        let end = if c + 1 < LENGTH_BASE.len() { LENGTH_BASE[c + 1] as usize } else { MAX_RUN + 1 };
        for e in t.iter_mut().take(end).skip(base as usize) {
            *e = c as u8;
        }
    }
    t
}

/// Huffman code lengths for `freq`, none longer than `limit`: when the optimal code is too deep,
/// the frequencies are halved (keeping every used symbol at 1 or more) and the code made again,
/// which flattens the tree until it fits. A lone used symbol gets a partner, so that the code is
/// complete.
fn huffman_lengths(freq: &[u32], limit: u32) -> Vec<u8> {
    let mut f: Vec<u32> = freq.to_vec();
    loop {
        let lengths = optimal_lengths(&f);
        if lengths.iter().all(|&l| l as u32 <= limit) {
            return lengths;
        }
        for x in f.iter_mut().filter(|x| **x > 0) {
            *x = (*x >> 1).max(1);
        }
    }
}

/// Optimal (unlimited) Huffman code lengths; symbols of frequency 0 get 0.
fn optimal_lengths(freq: &[u32]) -> Vec<u8> {
    let mut lengths = vec![0u8; freq.len()];
    let used: Vec<usize> = (0..freq.len()).filter(|&s| freq[s] > 0).collect();
    match used.len() {
        0 => return lengths,
        1 => {
            // One symbol: a one-bit code, with an unused partner for completeness.
            lengths[used[0]] = 1;
            lengths[if used[0] == 0 { 1 } else { 0 }] = 1;
            return lengths;
        }
        _ => {}
    }
    // Two queues instead of a heap (van Leeuwen): the leaves sorted by weight, and the internal
    // nodes, which are made in order of weight. Nodes: leaves 0..n in that order, internal after.
    let mut leaves: Vec<(u32, usize)> = used.iter().map(|&s| (freq[s], s)).collect();
    leaves.sort_unstable();
    let n = leaves.len();
    let mut weight: Vec<u64> = leaves.iter().map(|&(f, _)| f as u64).chain(std::iter::repeat_n(0, n - 1)).collect();
    let mut parent = vec![0usize; 2 * n - 1];
    let (mut leaf, mut inner) = (0, n);
    for next in n..2 * n - 1 {
        let mut take = || {
            // The lighter of the two queues' heads; a leaf on a tie.
            if leaf < n && (inner >= next || weight[leaf] <= weight[inner]) {
                leaf += 1;
                leaf - 1
            } else {
                inner += 1;
                inner - 1
            }
        };
        let (a, b) = (take(), take());
        weight[next] = weight[a] + weight[b];
        parent[a] = next;
        parent[b] = next;
    }
    let next = 2 * n - 1;
    // Depths from the root (the last node) down: a parent is always numbered after its children.
    let root = next - 1;
    let mut depth = vec![0u8; 2 * n - 1];
    for node in (0..root).rev() {
        depth[node] = depth[parent[node]] + 1;
    }
    for (k, &(_, s)) in leaves.iter().enumerate() {
        lengths[s] = depth[k];
    }
    lengths
}

/// Canonical codes for `lengths` (RFC 1951, 3.2.2), bit-reversed: deflate sends codes from their
/// first bit, and the writer fills bytes from the low bit.
fn canonical_codes(lengths: &[u8]) -> Vec<u16> {
    let mut count = [0u16; 16];
    for &l in lengths {
        count[l as usize] += 1;
    }
    count[0] = 0;
    let mut next = [0u16; 16];
    let mut code = 0u16;
    for bits in 1..16 {
        code = (code + count[bits - 1]) << 1;
        next[bits] = code;
    }
    lengths
        .iter()
        .map(|&l| {
            if l == 0 {
                return 0;
            }
            let c = next[l as usize];
            next[l as usize] += 1;
            c.reverse_bits() >> (16 - l as u32)
        })
        .collect()
}

/// HLIT, HDIST, HCLEN and the two codes' lengths, run-length coded with the code-length alphabet
/// (16: repeat the last 3-6 times, 17: 3-10 zeros, 18: 11-138 zeros).
fn write_code_lengths(out: &mut BitWriter, lit: &[u8], dist: &[u8]) {
    let all: Vec<u8> = lit.iter().chain(dist).copied().collect();
    // (symbol, extra bits' value)
    let mut symbols: Vec<(u8, u8)> = Vec::with_capacity(all.len());
    let mut i = 0;
    while i < all.len() {
        let l = all[i];
        let mut run = 1;
        while i + run < all.len() && all[i + run] == l {
            run += 1;
        }
        let mut left = run;
        if l == 0 {
            while left >= 11 {
                let r = left.min(138);
                symbols.push((18, (r - 11) as u8));
                left -= r;
            }
            if left >= 3 {
                symbols.push((17, (left - 3) as u8));
                left = 0;
            }
        } else {
            symbols.push((l, 0));
            left -= 1;
            while left >= 3 {
                let r = left.min(6);
                symbols.push((16, (r - 3) as u8));
                left -= r;
            }
        }
        symbols.extend(std::iter::repeat_n((l, 0), left));
        i += run;
    }
    let mut freq = [0u32; 19];
    for &(s, _) in &symbols {
        freq[s as usize] += 1;
    }
    let cl_lengths = huffman_lengths(&freq, MAX_CODE_LENGTH_BITS);
    let cl_codes = canonical_codes(&cl_lengths);
    let hclen = CODE_LENGTH_ORDER.iter().rposition(|&s| cl_lengths[s] > 0).map_or(4, |p| (p + 1).max(4));
    out.put((lit.len() - 257) as u64, 5);
    out.put((dist.len() - 1) as u64, 5);
    out.put((hclen - 4) as u64, 4);
    for &s in &CODE_LENGTH_ORDER[..hclen] {
        out.put(cl_lengths[s] as u64, 3);
    }
    for (s, extra) in symbols {
        out.put(cl_codes[s as usize] as u64, cl_lengths[s as usize] as u32);
        match s {
            16 => out.put(extra as u64, 2),
            17 => out.put(extra as u64, 3),
            18 => out.put(extra as u64, 7),
            _ => {}
        }
    }
}

/// Adds two tokens' bits (entries of `put_tokens`'s table; 0 adds none) to `buf` and stores the
/// word at `pos`, which moves on by the bytes completed.
#[inline(always)]
fn put_two(out: &mut [u8], pos: &mut usize, buf: &mut u64, count: &mut u32, a: u32, b: u32) {
    *buf |= ((a & 0xFF_FFFF) as u64) << *count;
    *count += a >> 24;
    *buf |= ((b & 0xFF_FFFF) as u64) << *count;
    *count += b >> 24;
    out[*pos..*pos + 8].copy_from_slice(&buf.to_le_bytes());
    let done = (*count / 8) as usize;
    *pos += done;
    *buf >>= 8 * done;
    *count &= 7;
}

/// Bits packed from the low end of each byte, as deflate wants them.
struct BitWriter {
    bytes: Vec<u8>,
    buf: u64,
    count: u32,
}

impl BitWriter {
    fn with_capacity(n: usize) -> BitWriter {
        BitWriter { bytes: Vec::with_capacity(n), buf: 0, count: 0 }
    }

    /// Appends the `n` (at most 32) low bits of `bits`.
    #[inline]
    fn put(&mut self, bits: u64, n: u32) {
        self.buf |= bits << self.count;
        self.count += n;
        if self.count >= 32 {
            self.bytes.extend_from_slice(&(self.buf as u32).to_le_bytes());
            self.buf >>= 32;
            self.count -= 32;
        }
    }

    /// Appends each token's bits from `bits_of` (code | count << 24): a whole word is stored after
    /// every two tokens and the position moves on by the bytes they completed, without branches.
    fn put_tokens(&mut self, tokens: &[u16], bits_of: &[u32]) {
        // Whole bytes first, so that the buffer holds fewer than 8 bits.
        while self.count >= 8 {
            self.bytes.push(self.buf as u8);
            self.buf >>= 8;
            self.count -= 8;
        }
        let mut pos = self.bytes.len();
        // A store writes 8 bytes at `pos`, which then moves by at most 6 for two tokens.
        self.bytes.resize(pos + 3 * tokens.len() + 8, 0);
        let (mut buf, mut count) = (self.buf, self.count);
        let out = &mut self.bytes[..];
        // Two tokens between stores: at most 7 + 2 x 21 bits, which a word holds. (The work is a
        // chain of dependent shifts and adds; fewer stores shorten it.)
        let mut pairs = tokens.chunks_exact(2);
        for pair in &mut pairs {
            let (a, b) = (bits_of[pair[0] as usize], bits_of[pair[1] as usize]);
            put_two(out, &mut pos, &mut buf, &mut count, a, b);
        }
        // A last odd token, with an entry of no bits beside it.
        for &t in pairs.remainder() {
            put_two(out, &mut pos, &mut buf, &mut count, bits_of[t as usize], 0);
        }
        self.bytes.truncate(pos);
        (self.buf, self.count) = (buf, count);
    }

    fn finish(mut self) -> Vec<u8> {
        let n = self.count.div_ceil(8) as usize;
        self.bytes.extend_from_slice(&self.buf.to_le_bytes()[..n]);
        self.bytes
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn inflate(z: &[u8]) -> Vec<u8> {
        miniz_oxide::inflate::decompress_to_vec_zlib(z).expect("a valid zlib stream")
    }

    #[test]
    fn streams_inflate_to_their_input() {
        let mut rng = crate::rng::Rng::new(11);
        let mut cases: Vec<Vec<u8>> = vec![
            vec![],
            vec![7],
            vec![7, 7],
            vec![7, 7, 7, 7],
            vec![0; 1000],                                              // runs longer than 258
            (0..=255u8).collect(),                                      // every literal once
            (0..70_000).map(|_| rng.range(0.0, 256.0) as u8).collect(), // noise
        ];
        // Planes: a run-heavy one, a skewed one, a noisy one, as PXR24 makes them.
        let mut planes = Vec::new();
        for row in 0..48 {
            for x in 0..1600 {
                planes.push(match row % 3 {
                    0 => u8::from(x % 97 == 0),
                    1 => (rng.range(-3.0, 3.0) as i32 + 128) as u8,
                    _ => rng.range(0.0, 256.0) as u8,
                });
            }
        }
        cases.push(planes);
        // Frequencies of a Fibonacci sequence make an optimal code deeper than 15 bits.
        let mut fib = Vec::new();
        let (mut p, mut q) = (1usize, 1usize);
        for s in 0..25u8 {
            fib.extend(std::iter::repeat_n(s, p).flat_map(|b| [b, 200]));
            (p, q) = (q, p + q);
        }
        cases.push(fib);
        for (k, input) in cases.iter().enumerate() {
            let z = zlib_rle(input);
            assert_eq!(inflate(&z), *input, "case {k} ({} bytes)", input.len());
        }
    }

    #[test]
    fn runs_and_skewed_bytes_compress() {
        let runs = vec![0u8; 100_000];
        assert!(zlib_rle(&runs).len() < 1_000);
        let skewed: Vec<u8> = (0..100_000u32).map(|i| if i % 10 == 0 { (i / 10 % 7) as u8 } else { 128 }).collect();
        assert!(zlib_rle(&skewed).len() < 30_000, "{}", zlib_rle(&skewed).len());
    }

    #[test]
    fn huffman_lengths_respect_their_limit_and_the_kraft_equality() {
        let mut freq = vec![0u32; SYMBOLS];
        let (mut p, mut q) = (1u32, 1u32);
        for f in freq.iter_mut().take(30) {
            *f = p;
            (p, q) = (q, p + q);
        }
        for limit in [7, 9, 15] {
            let l = huffman_lengths(&freq, limit);
            assert!(l.iter().all(|&x| x as u32 <= limit));
            let kraft: f64 = l.iter().filter(|&&x| x > 0).map(|&x| 0.5f64.powi(x as i32)).sum();
            assert!((kraft - 1.0).abs() < 1e-12, "limit {limit}: {kraft}");
        }
    }
}
