//! Plane polygons of change footprints (f64, the model's georeferenced x, y): convex hull, area,
//! point-in-polygon and the distance between two convex polygons, for regions and their fusion.

/// Convex hull (Andrew's monotone chain), counter-clockwise, without repeated first point.
/// Fewer than three distinct points give the points themselves.
pub fn convex_hull(points: &[[f64; 2]]) -> Vec<[f64; 2]> {
    let mut sorted: Vec<[f64; 2]> = points
        .iter()
        .copied()
        .filter(|p| p[0].is_finite() && p[1].is_finite())
        .collect();
    sorted.sort_by(|a, b| a[0].total_cmp(&b[0]).then(a[1].total_cmp(&b[1])));
    sorted.dedup();
    if sorted.len() < 3 {
        return sorted;
    }
    let cross = |o: [f64; 2], a: [f64; 2], b: [f64; 2]| {
        (a[0] - o[0]) * (b[1] - o[1]) - (a[1] - o[1]) * (b[0] - o[0])
    };
    let mut hull: Vec<[f64; 2]> = Vec::with_capacity(2 * sorted.len());
    for pass in 0..2 {
        let start = hull.len();
        let iter: Box<dyn Iterator<Item = &[f64; 2]>> = if pass == 0 {
            Box::new(sorted.iter())
        } else {
            Box::new(sorted.iter().rev())
        };
        for &p in iter {
            while hull.len() >= start + 2
                && cross(hull[hull.len() - 2], hull[hull.len() - 1], p) <= 0.0
            {
                hull.pop();
            }
            hull.push(p);
        }
        hull.pop();
    }
    hull
}

/// Area of a simple polygon (shoelace), always ≥ 0.
pub fn polygon_area(polygon: &[[f64; 2]]) -> f64 {
    let n = polygon.len();
    if n < 3 {
        return 0.0;
    }
    let twice: f64 = (0..n)
        .map(|i| {
            let a = polygon[i];
            let b = polygon[(i + 1) % n];
            a[0] * b[1] - b[0] * a[1]
        })
        .sum();
    0.5 * twice.abs()
}

/// Whether `p` lies inside (or on) a convex counter-clockwise polygon.
pub fn convex_contains(polygon: &[[f64; 2]], p: [f64; 2]) -> bool {
    let n = polygon.len();
    if n < 3 {
        return false;
    }
    (0..n).all(|i| {
        let a = polygon[i];
        let b = polygon[(i + 1) % n];
        (b[0] - a[0]) * (p[1] - a[1]) - (b[1] - a[1]) * (p[0] - a[0]) >= -1e-9
    })
}

/// Least width of a convex polygon (over its edge directions) and its extent across that
/// direction, metres; (0, longest span) for fewer than three points.
pub fn width_and_length(polygon: &[[f64; 2]]) -> (f64, f64) {
    let n = polygon.len();
    if n < 3 {
        let span = if n == 2 {
            ((polygon[0][0] - polygon[1][0]).powi(2) + (polygon[0][1] - polygon[1][1]).powi(2))
                .sqrt()
        } else {
            0.0
        };
        return (0.0, span);
    }
    let mut best = (f64::INFINITY, 0.0);
    for i in 0..n {
        let (a, b) = (polygon[i], polygon[(i + 1) % n]);
        let length = ((b[0] - a[0]).powi(2) + (b[1] - a[1]).powi(2)).sqrt();
        if length <= 0.0 {
            continue;
        }
        let (ux, uy) = ((b[0] - a[0]) / length, (b[1] - a[1]) / length);
        let (mut across_max, mut along_min, mut along_max) =
            (0.0f64, f64::INFINITY, f64::NEG_INFINITY);
        for p in polygon {
            let (dx, dy) = (p[0] - a[0], p[1] - a[1]);
            across_max = across_max.max((dx * uy - dy * ux).abs());
            let along = dx * ux + dy * uy;
            along_min = along_min.min(along);
            along_max = along_max.max(along);
        }
        if across_max < best.0 {
            best = (across_max, along_max - along_min);
        }
    }
    if best.0.is_finite() {
        best
    } else {
        (0.0, 0.0)
    }
}

fn point_segment_distance(p: [f64; 2], a: [f64; 2], b: [f64; 2]) -> f64 {
    let ab = [b[0] - a[0], b[1] - a[1]];
    let ap = [p[0] - a[0], p[1] - a[1]];
    let length_sq = ab[0] * ab[0] + ab[1] * ab[1];
    let t = if length_sq > 0.0 {
        ((ap[0] * ab[0] + ap[1] * ab[1]) / length_sq).clamp(0.0, 1.0)
    } else {
        0.0
    };
    let d = [ap[0] - t * ab[0], ap[1] - t * ab[1]];
    (d[0] * d[0] + d[1] * d[1]).sqrt()
}

fn segments_cross(a: [f64; 2], b: [f64; 2], c: [f64; 2], d: [f64; 2]) -> bool {
    let orient = |p: [f64; 2], q: [f64; 2], r: [f64; 2]| {
        (q[0] - p[0]) * (r[1] - p[1]) - (q[1] - p[1]) * (r[0] - p[0])
    };
    let (o1, o2) = (orient(a, b, c), orient(a, b, d));
    let (o3, o4) = (orient(c, d, a), orient(c, d, b));
    o1 * o2 < 0.0 && o3 * o4 < 0.0
}

/// Distance between two convex polygons (or point sets of one or two points): 0 when they
/// overlap or touch.
pub fn convex_distance(a: &[[f64; 2]], b: &[[f64; 2]]) -> f64 {
    if a.is_empty() || b.is_empty() {
        return f64::INFINITY;
    }
    if a.iter().any(|p| convex_contains(b, *p)) || b.iter().any(|p| convex_contains(a, *p)) {
        return 0.0;
    }
    let edges = |poly: &[[f64; 2]]| -> Vec<([f64; 2], [f64; 2])> {
        let n = poly.len();
        if n == 1 {
            return vec![(poly[0], poly[0])];
        }
        (0..n).map(|i| (poly[i], poly[(i + 1) % n])).collect()
    };
    let (edges_a, edges_b) = (edges(a), edges(b));
    let mut best = f64::INFINITY;
    for &(p, q) in &edges_a {
        for &(r, s) in &edges_b {
            if segments_cross(p, q, r, s) {
                return 0.0;
            }
            best = best
                .min(point_segment_distance(p, r, s))
                .min(point_segment_distance(q, r, s))
                .min(point_segment_distance(r, p, q))
                .min(point_segment_distance(s, p, q));
        }
    }
    best
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn hull_area_containment_and_distance_of_squares() {
        let mut points = vec![[0.0, 0.0], [2.0, 0.0], [2.0, 2.0], [0.0, 2.0], [1.0, 1.0]];
        points.push([1.0, 0.5]);
        let hull = convex_hull(&points);
        assert_eq!(hull.len(), 4);
        assert!((polygon_area(&hull) - 4.0).abs() < 1e-12);
        assert!(convex_contains(&hull, [1.5, 1.5]));
        let strip = convex_hull(&[[0.0, 0.0], [10.0, 0.0], [10.0, 0.5], [0.0, 0.5]]);
        let (width, length) = width_and_length(&strip);
        assert!((width - 0.5).abs() < 1e-12 && (length - 10.0).abs() < 1e-12);
        assert!(!convex_contains(&hull, [2.5, 1.5]));
        let shifted: Vec<[f64; 2]> = hull.iter().map(|p| [p[0] + 5.0, p[1]]).collect();
        assert!((convex_distance(&hull, &shifted) - 3.0).abs() < 1e-12);
        let overlapping: Vec<[f64; 2]> = hull.iter().map(|p| [p[0] + 1.0, p[1] + 1.0]).collect();
        assert_eq!(convex_distance(&hull, &overlapping), 0.0);
        // A cross: no vertex inside the other, edges cross.
        let wide = convex_hull(&[[-3.0, 0.9], [5.0, 0.9], [5.0, 1.1], [-3.0, 1.1]]);
        let tall = convex_hull(&[[0.9, -3.0], [1.1, -3.0], [1.1, 5.0], [0.9, 5.0]]);
        assert_eq!(convex_distance(&wide, &tall), 0.0);
    }
}
