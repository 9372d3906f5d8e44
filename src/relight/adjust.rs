//! A light turned about the world's up axis and made brighter or dimmer (`relight --rotate`,
//! `--intensity`): a sun's direction and a point light's position (about the vertical through
//! the body) turn, an environment map's columns shift, every radiance scales.

use crate::imageio::RgbImage;
use crate::light::{EnvironmentMap, Light};
use glam::{DMat3, DVec3};

/// `light` turned by `degrees` about the world's up (+Y, the environment maps' up; seen from
/// above, counter-clockwise), a point light about the vertical through `pivot`, and every
/// strength (irradiance, intensity, radiance, a map's scale, the ambient) times `intensity`.
pub fn adjusted(light: &Light, degrees: f64, intensity: f64, pivot: DVec3) -> Light {
    let turn = DMat3::from_rotation_y(degrees.to_radians());
    match light {
        Light::Directional { direction, irradiance, ambient } => {
            Light::Directional { direction: turn * *direction, irradiance: *irradiance * intensity, ambient: *ambient * intensity }
        }
        Light::Point { position, intensity: strength, ambient } => {
            Light::Point { position: pivot + turn * (*position - pivot), intensity: *strength * intensity, ambient: *ambient * intensity }
        }
        Light::Uniform { radiance } => Light::Uniform { radiance: *radiance * intensity },
        Light::Environment { path, scale, map } => Light::Environment { path: path.clone(), scale: scale * intensity, map: turned_map(map, degrees) },
        Light::Unknown { kind, strength, ambient } => Light::Unknown { kind: *kind, strength: strength.map(|s| s * intensity), ambient: *ambient * intensity },
    }
}

/// The largest strength `light` states (an irradiance, intensity or radiance channel, an
/// ambient's, an environment map's brightest texel times its scale): what must stay within the
/// scene format's bound once `--intensity` has scaled it.
pub fn peak_strength(light: &Light) -> f64 {
    match light {
        Light::Directional { irradiance, ambient, .. } => irradiance.max_element().max(ambient.max_element()),
        Light::Point { intensity, ambient, .. } => intensity.max_element().max(ambient.max_element()),
        Light::Uniform { radiance } => radiance.max_element(),
        Light::Environment { scale, map, .. } => map.image.pixels.iter().flatten().fold(0.0f64, |m, &c| m.max(c as f64)) * scale,
        Light::Unknown { strength, ambient, .. } => strength.map_or(0.0, |s| s.max_element()).max(ambient.max_element()),
    }
}

/// An equirectangular map turned by `degrees` about its up axis: a turn about +Y is a shift of
/// the columns (longitude), by a whole number of texels exactly, else each new texel mixing
/// the two it falls between (which keeps every row's sum, so the map's total radiance).
pub fn turned_map(map: &EnvironmentMap, degrees: f64) -> EnvironmentMap {
    let (w, h) = (map.image.width, map.image.height);
    // The radiance toward a turned direction at longitude phi is the old map's at phi + turn.
    let shift = (degrees / 360.0).rem_euclid(1.0) * w as f64;
    let whole = shift.floor() as usize;
    let part = (shift - shift.floor()) as f32;
    let mut image = RgbImage::new(w, h);
    for y in 0..h {
        for x in 0..w {
            let a = map.image.get((x + whole) % w, y);
            let b = map.image.get((x + whole + 1) % w, y);
            image.set(x, y, [0, 1, 2].map(|c| a[c] * (1.0 - part) + b[c] * part));
        }
    }
    EnvironmentMap { image }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn map() -> EnvironmentMap {
        let mut image = RgbImage::new(36, 18);
        for y in 0..18 {
            for x in 0..36 {
                image.set(x, y, [x as f32 + 0.5 * y as f32, (x * x % 7) as f32, 1.0 + y as f32]);
            }
        }
        EnvironmentMap { image }
    }

    #[test]
    fn a_turned_map_shows_the_old_radiance_in_the_turned_direction() {
        let map = map();
        // A whole number of texels (10 degrees on a 36-wide map): exact for any direction.
        for degrees in [10.0, 90.0, -30.0, 370.0] {
            let turned = turned_map(&map, degrees);
            let turn = DMat3::from_rotation_y(f64::to_radians(degrees));
            for d in [DVec3::new(0.3, 0.2, -0.9), DVec3::new(-0.7, -0.5, 0.1), DVec3::new(0.1, 0.9, 0.4)] {
                let d = d.normalize();
                let (old, new) = (map.lookup(d), turned.lookup(turn * d));
                assert!((old - new).length() < 1e-4 * (1.0 + old.length()), "{degrees}: {old} {new}");
            }
        }
    }

    #[test]
    fn a_fractional_turn_keeps_the_total_radiance() {
        let map = map();
        let turned = turned_map(&map, 12.5);
        assert!((map.mean_radiance() - turned.mean_radiance()).length() < 1e-5 * map.mean_radiance().length());
    }

    #[test]
    fn suns_and_lamps_turn_about_the_vertical_and_scale() {
        let sun = Light::Directional { direction: DVec3::new(1.0, 1.0, 0.0).normalize(), irradiance: DVec3::ONE, ambient: DVec3::splat(0.1) };
        let Light::Directional { direction, irradiance, ambient } = adjusted(&sun, 90.0, 2.0, DVec3::ZERO) else { panic!() };
        // +X turned a quarter counter-clockwise seen from above (+Y) is -Z.
        assert!((direction - DVec3::new(0.0, 1.0, -1.0).normalize()).length() < 1e-12, "{direction}");
        assert_eq!((irradiance, ambient), (DVec3::splat(2.0), DVec3::splat(0.2)));
        let lamp = Light::Point { position: DVec3::new(2.0, 3.0, 1.0), intensity: DVec3::ONE, ambient: DVec3::ZERO };
        let Light::Point { position, .. } = adjusted(&lamp, 180.0, 1.0, DVec3::new(1.0, 0.0, 1.0)) else { panic!() };
        assert!((position - DVec3::new(0.0, 3.0, 1.0)).length() < 1e-12, "{position}");
    }
}
