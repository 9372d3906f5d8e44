use super::*;

const DEFAULT: &str = DEFAULT_TEXT;

#[test]
fn default_schedule_parses_and_stages_in_order() {
    let s = Schedule::parse(DEFAULT, Path::new("schedules/default.toml")).unwrap();
    assert!(s.weight("grey", 0) > 0.0 && s.weight("rgb", 0) == 0.0, "segment 1 fits a grey silhouette");
    assert_eq!(s.weight("density", 0), 0.0);
    let late = s.iterations - 1;
    assert!(s.weight("rgb", late) > 0.9 && s.weight("grey", late) < 1e-9, "segment 3 fits colour");
    assert!(s.weight("density", late) > 0.0);
}

#[test]
fn ramps_interpolate_between_hold_and_hold_plus_ramp() {
    let r = Ramp { from: 1.0, to: 0.0, hold: 100.0, ramp: 50.0 };
    assert_eq!(r.at(0), 1.0);
    assert_eq!(r.at(100), 1.0);
    assert_eq!(r.at(125), 0.5);
    assert_eq!(r.at(150), 0.0);
    assert_eq!(r.at(1000), 0.0);
}

fn error_of(text: &str) -> ScheduleError {
    Schedule::parse(text, Path::new("s.toml")).unwrap_err()
}

#[test]
fn errors_name_the_file_and_key() {
    assert_eq!(error_of("iterations = -3\n[losses]\nmask = 1.0").key, "iterations");
    assert_eq!(error_of("iterations = 10\nbogus = 1\n[losses]\nmask = 1.0").key, "bogus");
    assert_eq!(error_of("[losses]\nmask = 1.0\nshine = 2.0").key, "losses.shine");
    assert_eq!(error_of("[losses]\nmask = 1.0\n[losses.rgb]\nfrom = 0.0\nto = 1.0\nhold = -5").key, "losses.rgb.hold");
    assert_eq!(error_of("iterations = 100\n[losses]\nmask = 1.0\n[losses.rgb]\nfrom = 0.0\nto = 1.0\nhold = 500").key, "losses.rgb.hold");
    assert_eq!(error_of("[losses]\nrgb = 1.0").key, "losses.mask");
    assert_eq!(error_of("[learning_rates]\nfield = 0\n[losses]\nmask = 1.0").key, "learning_rates.field");
    assert_eq!(error_of("[learning_rates]\nbrain = 1e-3\n[losses]\nmask = 1.0").key, "learning_rates.brain");
    assert_eq!(error_of("light = \"sometimes\"\n[losses]\nmask = 1.0").key, "light");
    assert_eq!(error_of("footprint = \"blurry\"\n[losses]\nmask = 1.0").key, "footprint");
    assert_eq!(error_of("[losses]\nmask = \"lots\"").key, "losses.mask");
    assert_eq!(error_of("[field]\nkind = \"voxels\"\n[losses]\nmask = 1.0").key, "field.kind");
    assert_eq!(error_of("[field]\nkind = \"grid\"\nlevels = 0\n[losses]\nmask = 1.0").key, "field.levels");
    assert_eq!(error_of("[field]\nlevels = 4\n[losses]\nmask = 1.0").key, "field.levels");
    assert_eq!(error_of("[field]\nkind = \"grid\"\ncells = 4\n[losses]\nmask = 1.0").key, "field.cells");
    assert_eq!(error_of("[losses]\nmask = nan").key, "losses.mask");
    assert_eq!(error_of("[losses]\nmask = 1\neikonal = -1").key, "losses.eikonal", "a shorthand's error names the key as written");
    assert_eq!(error_of("density_points = 0\n[losses]\nmask = 1.0\ndensity = 0.5").key, "density_points");
    assert_eq!(error_of("regulariser_points = 0\n[losses]\nmask = 1.0\ncurvature = 0.1").key, "regulariser_points");
    assert!(Schedule::parse("regulariser_points = 0\n[losses]\nmask = 1.0", Path::new("s.toml")).is_ok(), "no weight, no points needed");
    assert_eq!(error_of("[field]\nkind = \"grid\"\nreach_per_extent = 0\n[losses]\nmask = 1.0").key, "field.reach_per_extent");
    assert_eq!(error_of("[field]\nreach_per_extent = 0.2\n[losses]\nmask = 1.0").key, "field.reach_per_extent");
    assert_eq!(error_of("density_at_shadow_scale = \"yes\"\n[losses]\nmask = 1.0").key, "density_at_shadow_scale");
    let shadow_scale = |text: &str| Schedule::parse(text, Path::new("s.toml")).map(|s| (s.density_at_shadow_scale, s.error_rays)).ok();
    assert_eq!(shadow_scale("[losses]\nmask = 1.0"), Some((Switch::Fixed(false), ErrorRays::Share(0.0))), "both off unless a schedule asks");
    assert_eq!(shadow_scale("density_at_shadow_scale = true\nerror_rays = 0.5\n[losses]\nmask = 1.0"), Some((Switch::Fixed(true), ErrorRays::Share(0.5))));
    assert_eq!(shadow_scale("density_at_shadow_scale = \"auto\"\nerror_rays = \"auto\"\n[losses]\nmask = 1.0"), Some((Switch::Auto, ErrorRays::Auto)));
    assert_eq!((Switch::Auto.on(true), Switch::Auto.on(false), Switch::Fixed(true).on(false), Switch::Fixed(false).on(true)), (true, false, true, false));
    assert_eq!(error_of("error_rays = \"many\"\n[losses]\nmask = 1.0").key, "error_rays");
    assert_eq!((ErrorRays::Auto.share(true), ErrorRays::Auto.share(false), ErrorRays::Share(0.2).share(true)), (LOOSE_ERROR_RAYS, 0.0, 0.2));
    assert_eq!(error_of("cull_samples = \"yes\"\n[losses]\nmask = 1.0").key, "cull_samples");
    let parsed = |text: &str| Schedule::parse(text, Path::new("s.toml")).map(|s| s.cull_samples).ok();
    assert_eq!(parsed("[losses]\nmask = 1.0"), Some(true), "culling is on unless a schedule turns it off");
    assert_eq!(parsed("cull_samples = false\n[losses]\nmask = 1.0"), Some(false));
    assert_eq!(error_of("error_rays = -0.5\n[losses]\nmask = 1.0").key, "error_rays");
    // A key no schedule knows, at any level, names itself and the line.
    let unknown = error_of("iterations = 10\n\n[losses]\nmask = 1.0\n[losses.rgb]\nfrom = 1\nslope = 2");
    assert_eq!(unknown.key, "losses.rgb.slope");
    assert!(unknown.message.contains("unknown key") && unknown.message.ends_with("(line 7)"), "{unknown}");
    assert_eq!(error_of("[learning_rates]\nfield = \"fast\"\n[losses]\nmask = 1.0").key, "learning_rates.field");
    assert_eq!(error_of("iterations = 2.5\n[losses]\nmask = 1.0").key, "iterations");
    assert_eq!(error_of("density_at_shadow_scale = 1\n[losses]\nmask = 1.0").key, "density_at_shadow_scale");
    assert_eq!(error_of("[losses]\nmask = 1.0\n[losses.rgb]\nto = 1.0").key, "losses.rgb", "a ramp without its start");
    assert_eq!(error_of("[field]\nkind = \"grid\"\nfeatures = 0\n[losses]\nmask = 1.0").key, "field.features");
    assert_eq!(error_of("[field]\nkind = \"grid\"\nfinest_per_extent = 2.5\n[losses]\nmask = 1.0").key, "field.finest_per_extent");
    assert_eq!(error_of("[field]\nfinest_per_extent = 320\n[losses]\nmask = 1.0").key, "field.finest_per_extent");
    assert_eq!(error_of("[field]\nalbedo_layers = 9\n[losses]\nmask = 1.0").key, "field.albedo_layers");
    let shaped =
        Schedule::parse("[field]\nkind = \"grid\"\nfeatures = 4\nfinest_per_extent = 320\nalbedo_layers = 0\n[losses]\nmask = 1.0", Path::new("s.toml"))
            .unwrap();
    assert_eq!((shaped.field.features, shaped.field.finest_per_extent, shaped.field.albedo_layers), (Some(4), Some(320), Some(0)));
    let mlp = Schedule::parse("[field]\nkind = \"mlp\"\nalbedo_layers = 1\n[losses]\nmask = 1.0", Path::new("s.toml")).unwrap();
    assert_eq!(mlp.field.albedo_layers, Some(1), "either field may decode the albedo on its own");
    let loose = Schedule::parse("[field]\nkind = \"grid\"\nreach_per_extent = 0.2\n[losses]\nmask = 1.0", Path::new("s.toml")).unwrap();
    assert!(loose.field.reach_per_extent == Some(0.2));
    let e = error_of("iterations = [");
    assert!(e.to_string().starts_with("s.toml: (syntax)"), "{e}");
}

#[test]
fn coarse_to_fine_opens_the_finer_half_of_the_levels_between_its_iterations() {
    let s = Schedule::parse("[field]\nkind = \"grid\"\nfine_levels_from = 100\nfine_levels_until = 200\n[losses]\nmask = 1.0", Path::new("c.toml")).unwrap();
    assert_eq!(s.active_levels(8, 0), 4.0);
    assert_eq!(s.active_levels(8, 100), 4.0);
    assert_eq!(s.active_levels(8, 150), 6.0);
    assert_eq!(s.active_levels(8, 500), 8.0);
    let all = Schedule::parse("[field]\nkind = \"grid\"\n[losses]\nmask = 1.0", Path::new("a.toml")).unwrap();
    assert_eq!(all.active_levels(8, 0), 8.0);
    assert_eq!(error_of("[field]\nkind = \"grid\"\nfine_levels_from = 100\n[losses]\nmask = 1.0").key, "field.fine_levels_from");
    assert_eq!(error_of("[field]\nkind = \"grid\"\nfine_levels_from = 100\nfine_levels_until = 50\n[losses]\nmask = 1.0").key, "field.fine_levels_until");
}

#[test]
fn light_fitting_on_a_uniform_scene_is_an_error_that_says_why() {
    let fit = Schedule::parse("light = \"fit\"\n[losses]\nmask = 1.0", Path::new("fit.toml")).unwrap();
    let e = fit.check_against(false).unwrap_err();
    assert!(e.to_string().contains("fit.toml: light:") && e.to_string().contains("uniformly lit"), "{e}");
    assert!(fit.check_against(true).unwrap());
    let auto = Schedule::parse("[losses]\nmask = 1.0", Path::new("a.toml")).unwrap();
    assert!(!auto.check_against(false).unwrap());
    assert!(auto.check_against(true).unwrap());
}

#[test]
fn learning_rates_decay_exponentially_over_their_segment() {
    let s = Schedule::parse(
            "iterations = 1000\nlight_from = 200\nlight_lr_decay = 0.1\nfield_lr_decay = 0.01\nfield_lr_decay_from = 600\n[learning_rates]\nfield = 1.0\nfeatures = 1.0\nlight = 1.0\ngaussians = 1.0\n[losses]\nmask = 1.0",
            Path::new("d.toml"),
        )
        .unwrap();
    let close = |a: f64, b: f64| (a - b).abs() < 1e-12;
    assert!(close(s.learning_rate("field", 600), 1.0) && close(s.learning_rate("field", 800), 0.1) && close(s.learning_rate("field", 1000), 0.01));
    assert!(close(s.learning_rate("features", 800), 0.1), "the feature tables decay with the field");
    assert!(close(s.learning_rate("light", 200), 1.0) && close(s.learning_rate("light", 600), 0.1f64.sqrt()));
    assert!(close(s.learning_rate("gaussians", 999), 1.0), "the Gaussians keep their rate");
    assert_eq!(error_of("field_lr_decay = 0\n[losses]\nmask = 1.0").key, "field_lr_decay");
    assert_eq!(error_of("sun_search = -1\n[losses]\nmask = 1.0").key, "sun_search");
}

/// The top-level settings in which two schedules differ, in name order.
fn differing_settings(a: &Schedule, b: &Schedule) -> Vec<String> {
    let (a, b) = (serde_json::to_value(a).unwrap(), serde_json::to_value(b).unwrap());
    a.as_object().unwrap().iter().filter(|(k, v)| b.get(k.as_str()) != Some(v)).map(|(k, _)| k.clone()).collect()
}

/// The shipped longer schedule is the default but for its length and where the field's
/// learning rates start to fall (a stale copy of an older default would differ in more).
#[test]
fn the_detail_schedule_is_the_default_made_longer() {
    let path = Path::new(env!("CARGO_MANIFEST_DIR")).join("schedules/detail.toml");
    let detail = Schedule::parse(&std::fs::read_to_string(&path).unwrap(), Path::new("x.toml")).unwrap();
    let default = Schedule::parse(DEFAULT, Path::new("x.toml")).unwrap();
    assert!(detail.iterations > default.iterations && detail.field_lr_decay_from > default.field_lr_decay_from);
    assert!(detail.iterations - detail.field_lr_decay_from >= default.iterations - default.field_lr_decay_from, "a tail no shorter");
    assert_eq!(differing_settings(&detail, &default), ["field_lr_decay_from", "iterations"]);
    // It is the default stretched to its length, to the nearest hundred.
    let stretched = default.stretched(detail.iterations);
    assert_eq!(stretched.iterations, detail.iterations);
    assert!(stretched.field_lr_decay_from.abs_diff(detail.field_lr_decay_from) <= 50, "{} vs {}", stretched.field_lr_decay_from, detail.field_lr_decay_from);
    assert!(differing_settings(&stretched, &detail).iter().all(|s| *s == "field_lr_decay_from"));
}

/// Every shipped ablation parses and differs from the default schedule (in its settings,
/// not only its comments).
#[test]
fn shipped_ablations_parse_and_differ_from_the_default() {
    let folder = Path::new(env!("CARGO_MANIFEST_DIR")).join("schedules/ablations");
    let default = Schedule::parse(DEFAULT, Path::new("x.toml")).unwrap();
    let mut count = 0;
    for entry in std::fs::read_dir(&folder).unwrap().flatten() {
        let path = entry.path();
        let text = std::fs::read_to_string(&path).unwrap();
        let ablation = Schedule::parse(&text, Path::new("x.toml")).unwrap_or_else(|e| panic!("{}: {e}", path.display()));
        assert_ne!(ablation, default, "{} is the default schedule", path.display());
        // One respect: the settings that differ share one top-level key (a stale copy of
        // an older default would differ in more).
        let keys = differing_settings(&ablation, &default);
        assert_eq!(keys.len(), 1, "{} differs from the default in {keys:?}", path.display());
        count += 1;
    }
    assert!(count >= 8, "{count} ablations in {}", folder.display());
}

/// A step samples the early fine and probe counts before `early_samples_until` and the late
/// ones from it; a schedule that names no early count samples its late count throughout.
#[test]
fn the_fine_and_probe_samples_drop_to_their_late_counts_at_early_samples_until() {
    let default = Schedule::parse(DEFAULT, Path::new("x.toml")).unwrap();
    let until = default.early_samples_until;
    assert!(until > 0 && default.early_fine_samples_per_ray != default.fine_samples_per_ray);
    assert_eq!(default.sampling(0).fine, default.early_fine_samples_per_ray);
    assert_eq!(default.sampling(until - 1).fine, default.early_fine_samples_per_ray);
    assert_eq!(default.sampling(until).fine, default.fine_samples_per_ray);
    // The probe samples drop with them; the coarse ones stay, and a batch's draws follow.
    assert!(default.early_probe_samples_per_ray != default.probe_samples_per_ray);
    assert_eq!(default.sampling(until - 1).probe, default.early_probe_samples_per_ray);
    assert_eq!(default.sampling(until).probe, default.probe_samples_per_ray);
    assert_eq!(default.sampling(0).coarse, default.sampling(until).coarse);
    assert_eq!(
        default.sampling(until - 1).draws() - default.sampling(until).draws(),
        default.early_fine_samples_per_ray - default.fine_samples_per_ray + default.early_probe_samples_per_ray - default.probe_samples_per_ray
    );
    let plain = Schedule::parse("iterations = 100\nfine_samples_per_ray = 12\nprobe_samples_per_ray = 6\n[losses]\nmask = 1.0", Path::new("x.toml")).unwrap();
    assert!([0, 50, 99].iter().all(|&it| plain.sampling(it).fine == 12 && plain.sampling(it).probe == 6));
    assert_eq!((plain.fine_samples_label(), plain.probe_samples_label()), ("12".to_string(), "6".to_string()));
    assert_eq!(default.fine_samples_label(), format!("{} ({} from {until})", default.early_fine_samples_per_ray, default.fine_samples_per_ray));
    assert_eq!(default.probe_samples_label(), format!("{} ({} from {until})", default.early_probe_samples_per_ray, default.probe_samples_per_ray));
    assert_eq!(error_of("iterations = 10\nearly_fine_samples_per_ray = -1\n[losses]\nmask = 1.0").key, "early_fine_samples_per_ray");
    assert_eq!(error_of("iterations = 10\nearly_probe_samples_per_ray = 1.5\n[losses]\nmask = 1.0").key, "early_probe_samples_per_ray");
}

/// With lazy regularisation the regulariser points' inputs are computed every other step and
/// their terms weigh twice as much; every other term is untouched. `auto` is on for a tight
/// body alone, and reads as off until resolved.
#[test]
fn lazy_regularisation_evaluates_the_regulariser_terms_every_other_step_at_twice_their_weight() {
    use crate::losses::Input;
    let parse =
        |lazy: &str| Schedule::parse(&format!("iterations = 10\n{lazy}[losses]\nmask = 1.0\neikonal = 0.1\ncurvature = 0.05"), Path::new("s.toml")).unwrap();
    let (each, every) = (parse(""), parse("lazy_regularisation = true\n"));
    assert_eq!((each.regularise_every, every.regularise_every), (1, LAZY_EVERY), "absent: every step");
    for it in 0..4 {
        assert!(each.needs(Input::Gradient, it) && each.needs(Input::NormalPairs, it));
        assert_eq!(every.needs(Input::Gradient, it), it % 2 == 0);
        assert_eq!(every.needs(Input::NormalPairs, it), it % 2 == 0);
        assert!((every.weight("eikonal", it) - 2.0 * each.weight("eikonal", it)).abs() < 1e-12);
        assert!((every.weight("curvature", it) - 2.0 * each.weight("curvature", it)).abs() < 1e-12);
        assert_eq!(every.weight("mask", it), each.weight("mask", it));
        assert!(every.needs(Input::Colour, it) == each.needs(Input::Colour, it));
    }
    let auto = parse("lazy_regularisation = \"auto\"\n");
    assert_eq!(auto.regularise_every, 1, "unresolved: every step");
    assert_eq!(auto.clone().with_lazy_regularisation(true).regularise_every, LAZY_EVERY);
    assert_eq!(auto.with_lazy_regularisation(false).regularise_every, 1, "a loose body regularises every step");
    assert_eq!(every.with_lazy_regularisation(false).regularise_every, LAZY_EVERY, "on is on");
    assert_eq!(error_of("iterations = 10\nlazy_regularisation = 2\n[losses]\nmask = 1.0").key, "lazy_regularisation");
}
