//! Polygons in image pixels filled into masks: the ego body's (`EgoMask`'s params and built-in
//! rigs) and hand-labelled regions (`eval::labels`).

/// A polygon's vertices, in image pixels: x right, y down, the pixel (i, j) covering
/// [i, i+1) x [j, j+1). Closed implicitly.
pub type Polygon = Vec<(i32, i32)>;

/// The pixels of a `w` x `h` image whose centres lie inside the polygons (even-odd rule over
/// all of them together, so a polygon inside another cuts a hole), as 1 in a row-major map.
pub fn fill_polygons(w: u32, h: u32, polygons: &[Polygon]) -> Vec<u8> {
    let exact: Vec<Vec<(f64, f64)>> =
        polygons.iter().map(|p| p.iter().map(|&(x, y)| (x as f64, y as f64)).collect()).collect();
    fill_polygons_f64(w, h, &exact)
}

/// [`fill_polygons`] with vertices anywhere (hand labels in the convention of OpenCV's
/// `fillPoly`, where the pixel (i, j) is the point (i, j), are these shifted by half a pixel).
pub fn fill_polygons_f64(w: u32, h: u32, polygons: &[Vec<(f64, f64)>]) -> Vec<u8> {
    let (w, h) = (w as usize, h as usize);
    let mut out = vec![0u8; w * h];
    let mut crossings: Vec<f64> = Vec::new();
    for y in 0..h {
        let cy = y as f64 + 0.5;
        crossings.clear();
        for p in polygons {
            for k in 0..p.len() {
                let (a, b) = (p[k], p[(k + 1) % p.len()]);
                let (ay, by) = (a.1, b.1);
                // Half-open in y, so a vertex on the scanline is counted once.
                if (ay <= cy) != (by <= cy) {
                    let t = (cy - ay) / (by - ay);
                    crossings.push(a.0 + t * (b.0 - a.0));
                }
            }
        }
        crossings.sort_by(f64::total_cmp);
        for pair in crossings.chunks_exact(2) {
            // Pixels whose centre x + 0.5 lies in [pair[0], pair[1]).
            let first = (pair[0] - 0.5).ceil().clamp(0.0, w as f64) as usize;
            let end = (pair[1] - 0.5).ceil().clamp(0.0, w as f64) as usize;
            for v in &mut out[y * w + first.min(end)..y * w + end] {
                *v = 1;
            }
        }
    }
    out
}

/// The union of `polygons` drawn one by one (so overlapping ones never cut holes), with vertices
/// in OpenCV's `fillPoly` convention (the pixel (i, j) is the point (i, j)): hand labels and the
/// built-in rigs.
pub fn fill_opencv_polygons<'a>(w: u32, h: u32, polygons: impl IntoIterator<Item = &'a Vec<[f64; 2]>>) -> Vec<u8> {
    let mut out = vec![0u8; (w * h) as usize];
    for p in polygons {
        let shifted: Vec<(f64, f64)> = p.iter().map(|&[x, y]| (x + 0.5, y + 0.5)).collect();
        for (o, v) in out.iter_mut().zip(fill_polygons_f64(w, h, &[shifted])) {
            *o |= v;
        }
    }
    out
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_pixel_is_inside_when_its_centre_is() {
        // The square from (1, 1) to (4, 3): pixels x 1..4, y 1..3.
        let m = fill_polygons(6, 5, &[vec![(1, 1), (4, 1), (4, 3), (1, 3)]]);
        let inside: Vec<(usize, usize)> = (0..30).filter(|&i| m[i] == 1).map(|i| (i % 6, i / 6)).collect();
        assert_eq!(inside, vec![(1, 1), (2, 1), (3, 1), (1, 2), (2, 2), (3, 2)]);
        // A triangle: its area in pixels is near its geometric area.
        let t = fill_polygons(100, 100, &[vec![(0, 100), (100, 100), (100, 0)]]);
        let n = t.iter().filter(|&&v| v == 1).count() as f64;
        assert!((n - 5000.0).abs() < 101.0, "{n}");
        // A polygon inside another cuts a hole; vertices beyond the image are clipped.
        let holed = fill_polygons(
            10,
            10,
            &[vec![(-5, -5), (15, -5), (15, 15), (-5, 15)], vec![(2, 2), (8, 2), (8, 8), (2, 8)]],
        );
        assert_eq!(holed.iter().filter(|&&v| v == 1).count(), 100 - 36);
    }
}
