//! A shadow ray's segment and the culling test both shadow paths share: does it pass within a
//! radius of a point.

/// A ray segment `origin + t direction`, `t` in `[t0, t1]` (`t1` may be infinite).
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct ShadowRay {
    pub origin: [f32; 3],
    pub direction: [f32; 3],
    pub t0: f32,
    pub t1: f32,
}

/// Whether the segment comes within `sqrt(radius2)` of `centre`.
#[inline]
pub(super) fn segment_within(centre: [f32; 3], ray: &ShadowRay, radius2: f32) -> bool {
    if radius2 < 0.0 {
        return false;
    }
    let v = [centre[0] - ray.origin[0], centre[1] - ray.origin[1], centre[2] - ray.origin[2]];
    let along = (v[0] * ray.direction[0] + v[1] * ray.direction[1] + v[2] * ray.direction[2]).clamp(ray.t0, ray.t1);
    let d = [v[0] - along * ray.direction[0], v[1] - along * ray.direction[1], v[2] - along * ray.direction[2]];
    d[0] * d[0] + d[1] * d[1] + d[2] * d[2] <= radius2
}
