//! Loose clothing for the synthetic characters: rigid shapes carried by one bone whose surfaces
//! lie 15-30 cm from every bone (a bell skirt on the pelvis, a backpack on the chest, a bun on
//! the head), each with an exact signed distance and its gradient in the bone's rest frame.
//! They are what a prior of capsules around the bones does not flatter.

use glam::{DVec2, DVec3};

/// A shape in its bone's local frame (origin at the bone's head, +Y along the bone).
#[derive(Clone, Copy, Debug)]
pub enum Shape {
    /// A solid frustum about the bone's Y axis: radius `top_radius` at `top`, `bottom_radius`
    /// at `bottom` (below), linear in between.
    Frustum {
        top: f64,
        bottom: f64,
        top_radius: f64,
        bottom_radius: f64,
    },
    /// A box with rounded edges: centre, half extents (to the rounded surface) and rounding.
    RoundedBox {
        centre: DVec3,
        half: DVec3,
        rounding: f64,
    },
    Sphere {
        centre: DVec3,
        radius: f64,
    },
}

/// A garment: a shape carried rigidly by one bone, and its colour.
#[derive(Clone, Copy, Debug)]
pub struct Garment {
    pub name: &'static str,
    pub bone: usize,
    pub shape: Shape,
    pub colour: [f64; 3],
}

/// The human's loose clothes (bone indices of `human_specs`: 0 pelvis, 2 chest, 4 head).
pub fn dressed_human() -> Vec<Garment> {
    vec![
        // Waist 1.02 m, hem 0.56 m above the ground, 0.36 m wide at the hem: the hem lies
        // 0.25-0.3 m from the thighs inside it.
        Garment {
            name: "skirt",
            bone: 0,
            shape: Shape::Frustum { top: 0.10, bottom: -0.36, top_radius: 0.15, bottom_radius: 0.36 },
            colour: [0.70, 0.22, 0.25],
        },
        // On the back of the chest, its back face 0.26 m behind the spine.
        Garment {
            name: "backpack",
            bone: 2,
            shape: Shape::RoundedBox { centre: DVec3::new(0.0, 0.10, -0.19), half: DVec3::new(0.15, 0.17, 0.07), rounding: 0.03 },
            colour: [0.25, 0.50, 0.30],
        },
        // A bun at the back of the head, 0.21 m from the head's bone at its far side.
        Garment { name: "bun", bone: 4, shape: Shape::Sphere { centre: DVec3::new(0.0, 0.13, -0.13), radius: 0.08 }, colour: [0.35, 0.22, 0.12] },
    ]
}

impl Shape {
    /// Signed distance and its gradient at a bone-local point.
    pub fn sdf(&self, p: DVec3) -> (f64, DVec3) {
        match *self {
            Shape::Frustum { top, bottom, top_radius, bottom_radius } => frustum(p, top, bottom, top_radius, bottom_radius),
            Shape::RoundedBox { centre, half, rounding } => rounded_box(p - centre, half, rounding),
            Shape::Sphere { centre, radius } => {
                let r = p - centre;
                let length = r.length();
                (length - radius, if length > 1e-12 { r / length } else { DVec3::X })
            }
        }
    }

    /// The same shape `scale` times larger about its bone's head.
    pub fn scaled(&self, scale: f64) -> Self {
        match *self {
            Shape::Frustum { top, bottom, top_radius, bottom_radius } => {
                Shape::Frustum { top: top * scale, bottom: bottom * scale, top_radius: top_radius * scale, bottom_radius: bottom_radius * scale }
            }
            Shape::RoundedBox { centre, half, rounding } => Shape::RoundedBox { centre: centre * scale, half: half * scale, rounding: rounding * scale },
            Shape::Sphere { centre, radius } => Shape::Sphere { centre: centre * scale, radius: radius * scale },
        }
    }

    /// How far (m) the shape reaches from a bone segment of `length` along +Y from the origin.
    pub fn reach(&self, length: f64) -> f64 {
        let (lo, hi) = match *self {
            Shape::Frustum { top, bottom, top_radius, bottom_radius } => {
                let r = top_radius.max(bottom_radius);
                (DVec3::new(-r, bottom, -r), DVec3::new(r, top, r))
            }
            Shape::RoundedBox { centre, half, .. } => (centre - half, centre + half),
            Shape::Sphere { centre, radius } => (centre - DVec3::splat(radius), centre + DVec3::splat(radius)),
        };
        let mut reach = 0.0f64;
        for k in 0..8 {
            let corner = DVec3::new(if k & 1 == 0 { lo.x } else { hi.x }, if k & 2 == 0 { lo.y } else { hi.y }, if k & 4 == 0 { lo.z } else { hi.z });
            let on_bone = DVec3::new(0.0, corner.y.clamp(0.0, length), 0.0);
            reach = reach.max((corner - on_bone).length());
        }
        reach
    }
}

/// The solid frustum as a 2D region in (radial distance, height): a trapezoid whose left side
/// is the axis. The distance is to its three other sides; inside, it is negative.
fn frustum(p: DVec3, top: f64, bottom: f64, top_radius: f64, bottom_radius: f64) -> (f64, DVec3) {
    let radial = (p.x * p.x + p.z * p.z).sqrt();
    let q = DVec2::new(radial, p.y);
    let sides = [
        (DVec2::new(0.0, top), DVec2::new(top_radius, top)),
        (DVec2::new(top_radius, top), DVec2::new(bottom_radius, bottom)),
        (DVec2::new(bottom_radius, bottom), DVec2::new(0.0, bottom)),
    ];
    let (mut best, mut nearest) = (f64::INFINITY, q);
    for (a, b) in sides {
        let ab = b - a;
        let t = ((q - a).dot(ab) / ab.length_squared()).clamp(0.0, 1.0);
        let c = a + ab * t;
        let d = (q - c).length();
        if d < best {
            best = d;
            nearest = c;
        }
    }
    let height = (p.y - bottom) / (top - bottom);
    let inside = (0.0..=1.0).contains(&height) && radial <= bottom_radius + (top_radius - bottom_radius) * height;
    let sign = if inside { -1.0 } else { 1.0 };
    // The 2D gradient points from the nearest boundary point to q (away from it inside).
    let away = if best > 1e-12 { (q - nearest) / best * sign } else { DVec2::new(1.0, 0.0) };
    let radial_direction = if radial > 1e-12 { DVec3::new(p.x / radial, 0.0, p.z / radial) } else { DVec3::X };
    (sign * best, radial_direction * away.x + DVec3::Y * away.y)
}

/// A box of half extents `half` (to its rounded surface) with edges rounded by `rounding`,
/// centred at the origin.
fn rounded_box(p: DVec3, half: DVec3, rounding: f64) -> (f64, DVec3) {
    let q = p.abs() - (half - DVec3::splat(rounding));
    let outside = q.max(DVec3::ZERO);
    let outside_length = outside.length();
    let sign = DVec3::new(p.x.signum(), p.y.signum(), p.z.signum());
    if outside_length > 0.0 {
        return (outside_length - rounding, outside / outside_length * sign);
    }
    // Inside the inner box: the nearest face is along the largest q.
    let (axis, largest) = if q.x >= q.y && q.x >= q.z {
        (DVec3::X, q.x)
    } else if q.y >= q.z {
        (DVec3::Y, q.y)
    } else {
        (DVec3::Z, q.z)
    };
    (largest - rounding, axis * sign)
}

#[cfg(test)]
mod tests {
    use super::*;

    fn finite_difference(shape: &Shape, p: DVec3) -> DVec3 {
        let h = 1e-7;
        let f = |d: DVec3| (shape.sdf(p + d * h).0 - shape.sdf(p - d * h).0) / (2.0 * h);
        DVec3::new(f(DVec3::X), f(DVec3::Y), f(DVec3::Z))
    }

    #[test]
    fn every_shape_is_a_distance_with_its_exact_gradient() {
        let mut stream = crate::random::Stream::new(5, 6, 7);
        for garment in dressed_human() {
            let mut checked = 0;
            for _ in 0..2000 {
                let p = DVec3::new(stream.uniform() - 0.5, stream.uniform() - 0.6, stream.uniform() - 0.5) * 1.0;
                let (d, g) = garment.shape.sdf(p);
                let fd = finite_difference(&garment.shape, p);
                // Away from the medial set (where the gradient jumps) the two agree.
                if (fd.length() - 1.0).abs() < 1e-4 {
                    assert!((g - fd).length() < 1e-5, "{}: {p}: {g} vs {fd}", garment.name);
                    checked += 1;
                }
                assert!((g.length() - 1.0).abs() < 1e-9, "{}: gradient not unit at {p}", garment.name);
                // Lipschitz 1: the distance cannot change faster than the point moves.
                let q = p + DVec3::new(0.01, -0.02, 0.015);
                assert!((garment.shape.sdf(q).0 - d).abs() <= (q - p).length() + 1e-12, "{}", garment.name);
            }
            assert!(checked > 1500, "{}: {checked}", garment.name);
        }
    }

    #[test]
    fn shapes_have_their_stated_size() {
        let skirt = Shape::Frustum { top: 0.1, bottom: -0.36, top_radius: 0.15, bottom_radius: 0.36 };
        assert!((skirt.sdf(DVec3::new(0.36, -0.36 + 1e-9, 0.0)).0).abs() < 1e-8);
        assert!((skirt.sdf(DVec3::new(0.0, -0.46, 0.0)).0 - 0.1).abs() < 1e-12);
        assert!((skirt.sdf(DVec3::new(0.0, 0.0, 0.0)).0 + 0.1).abs() < 1e-12);
        let pack = Shape::RoundedBox { centre: DVec3::ZERO, half: DVec3::new(0.15, 0.17, 0.07), rounding: 0.03 };
        assert!((pack.sdf(DVec3::new(0.0, 0.0, 0.17)).0 - 0.1).abs() < 1e-12);
        assert!((pack.sdf(DVec3::ZERO).0 + 0.07).abs() < 1e-12);
        // The skirt's hem reaches 0.36 m out and 0.36 m below the pelvis's head.
        assert!((skirt.reach(0.12) - (2.0f64 * 0.36 * 0.36 + 0.36 * 0.36).sqrt()).abs() < 1e-12);
    }
}
