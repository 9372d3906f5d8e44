//! Render time per view of a fitted run (`umbra bench render RUN`): one test view (its camera
//! and frame) in the fitted light, under a sun, a point light and a sky at 64 samples per pixel,
//! timed with every thread and inside a one-thread pool, the ratio taken in the same run; the
//! view in all four lights from one trace against the four renders; then the evaluation's way,
//! a batch of views one after another against several at once.

use super::fit::peak_rss_mib;
use crate::backend::Backend;
use crate::eval::{render_view, render_view_layers, render_view_lights, Lighting, Strata, VIEW_SAMPLING};
use crate::fit_error::{io, FitError};
use crate::light::Light;
use crate::plot::BarChart;
use burn::module::Module;
use glam::DVec3;
use rayon::prelude::*;
use std::path::Path;

/// Sky samples per pixel the benchmark renders an environment with (the figure).
const SKY_SAMPLES: usize = 64;

/// How many times its width and height the size row renders a view at (16x the pixels: a
/// 128 x 128 capture rendered at 512 x 512).
const ENLARGE: usize = 4;

/// Seconds for one view in the fitted light at the capture's size and at `ENLARGE` times it.
fn size_cost(
    model: &crate::avatar::Avatar,
    scene: &crate::scene::Scene,
    camera: usize,
    frame: usize,
    device: &burn::tensor::Device,
    budget: f64,
) -> (f64, f64) {
    let fitted = Lighting::Fitted(0);
    let native = super::time(budget, || {
        render_view(model, scene, camera, frame, VIEW_SAMPLING, device, &fitted);
    });
    let _ = scene.footprint();
    let mut enlarged_scene = scene.clone();
    let c = &scene.cameras[camera];
    enlarged_scene.cameras[camera] = c.resized(c.width * ENLARGE, c.height * ENLARGE);
    let enlarged = super::time(budget, || {
        render_view(model, &enlarged_scene, camera, frame, VIEW_SAMPLING, device, &fitted);
    });
    (native, enlarged)
}

/// Measures `run`'s renders; writes `render.{md,csv,png}` into `out`, returns the Markdown.
pub fn render(run: &Path, out: &Path, quick: bool) -> Result<String, FitError> {
    let restored = crate::run::restore(run, None, Backend::Flex)?;
    let scene = &restored.scene;
    let model = restored.fitted.model.valid();
    let device = restored.fitted.device.clone().without_autodiff();
    let albedo_scale = crate::run::albedo_scale(scene, &model);
    let view = scene
        .views_in(crate::scene::Split::Test)
        .next()
        .or(scene.views.first())
        .ok_or_else(|| FitError::Input(format!("{}: the scene has no images", scene.root.display())))?;
    let (camera, frame) = (view.camera, view.frame);
    let budget = if quick { 0.0 } else { 2.0 };
    let threads = rayon::current_num_threads();
    let (sun, lamp, sky) = lights(scene, frame);
    let known = |light| Lighting::Known { light, albedo_scale, samples: SKY_SAMPLES };
    let cases: [(&str, Lighting); 4] = [
        ("fitted light (sun with Gaussian shadows)", Lighting::Fitted(0)),
        ("a sun", known(&sun)),
        ("a point light", known(&lamp)),
        ("an environment, 64 samples per pixel", known(&sky)),
    ];
    let one_thread = rayon::ThreadPoolBuilder::new().num_threads(1).build().map_err(|e| FitError::Input(format!("a one-thread pool: {e}")))?;
    let mut rows: Vec<(String, f64, f64)> = Vec::new();
    for (name, lighting) in &cases {
        let all = super::time(budget, || {
            render_view(&model, scene, camera, frame, VIEW_SAMPLING, &device, lighting);
        });
        let one = one_thread.install(|| {
            super::time(budget, || {
                render_view(&model, scene, camera, frame, VIEW_SAMPLING, &device, lighting);
            })
        });
        rows.push((name.to_string(), all, one));
    }
    // The view in all four lights from one trace (as the evaluation renders a view its test set
    // has in several lights), against the four renders above.
    let lightings: Vec<Lighting> = cases.iter().map(|(_, lighting)| *lighting).collect();
    let shared = super::time(budget, || {
        render_view_lights(&model, scene, camera, frame, VIEW_SAMPLING, &device, &lightings, None, Strata::Shortcuts);
    });
    let lights_at_once = (lightings.len(), shared, rows.iter().map(|r| r.1).sum::<f64>());
    // The evaluation's way: `threads` views of the fitted light one after another, and at once.
    let views: Vec<(usize, usize)> = scene.views_in(crate::scene::Split::Test).map(|v| (v.camera, v.frame)).take(threads.max(2)).collect();
    let fitted = Lighting::Fitted(0);
    let start = std::time::Instant::now();
    for &(c, f) in &views {
        render_view(&model, scene, c, f, VIEW_SAMPLING, &device, &fitted);
    }
    let sequential = start.elapsed().as_secs_f64() / views.len().max(1) as f64;
    let start = std::time::Instant::now();
    views.par_iter().for_each(|&(c, f)| {
        render_view(&model, scene, c, f, VIEW_SAMPLING, &device, &fitted);
    });
    let together = start.elapsed().as_secs_f64() / views.len().max(1) as f64;
    let (native, enlarged) = size_cost(&model, scene, camera, frame, &device, budget);

    // An area capture's refined pixels with every stratum traced, against the shortcuts every
    // render takes (`eval::Strata`), each view with its albedo as the evaluation renders it.
    let area = scene.footprint().footprint == crate::scene::Footprint::Area;
    let strata_views: Vec<(usize, usize)> = scene.views_in(crate::scene::Split::Test).map(|v| (v.camera, v.frame)).take(if quick { 2 } else { 8 }).collect();
    let strata_times = area.then(|| {
        [Strata::Traced, Strata::Shortcuts].map(|strata| {
            let start = std::time::Instant::now();
            strata_views.par_iter().for_each(|&(c, f)| {
                render_view_layers(&model, scene, c, f, VIEW_SAMPLING, &device, &fitted, Some(albedo_scale), strata);
            });
            start.elapsed().as_secs_f64() / strata_views.len().max(1) as f64
        })
    });
    let timings =
        Timings { rows, lights_at_once, views: views.len(), sequential, together, native, enlarged, strata: strata_times.map(|t| (t, strata_views.len())) };
    write_tables(run, out, &scene.cameras[camera], (camera, frame), &timings)
}

/// What `render` measured, in seconds per view.
struct Timings {
    /// Per light: all threads, one thread.
    rows: Vec<(String, f64, f64)>,
    /// The view in every light of `rows` from one trace: how many lights, its time and the sum
    /// of their renders on their own (all threads).
    lights_at_once: (usize, f64, f64),
    /// Test views rendered one after another, and at once.
    views: usize,
    sequential: f64,
    together: f64,
    /// The view at its size and at `ENLARGE` times it.
    native: f64,
    enlarged: f64,
    /// An area capture's views with every stratum traced and with the shortcuts, and how many.
    strata: Option<([f64; 2], usize)>,
}

/// A sun, a point light and a sky placed for the body in `frame`.
fn lights(scene: &crate::scene::Scene, frame: usize) -> (Light, Light, Light) {
    let (lo, hi) = scene.frames[frame].pose.bounds(&scene.skeleton);
    let extent = scene.body_extent();
    let up = crate::relight::world_up(&scene.cameras);
    let sun = Light::Directional { direction: (up + DVec3::new(0.4, 0.0, 0.3)).normalize(), irradiance: DVec3::ONE, ambient: DVec3::splat(0.1) };
    let lamp = Light::Point {
        position: (lo + hi) * 0.5 + (up + DVec3::new(0.5, 0.0, 0.5)).normalize() * extent,
        intensity: DVec3::splat(extent * extent),
        ambient: DVec3::splat(0.1),
    };
    let sky = Light::Environment { path: "synthetic sky".into(), scale: 1.0, map: crate::synth::synthetic_sky(128, 64) };
    (sun, lamp, sky)
}

/// render.md, render.csv and render.png; the Markdown.
fn write_tables(run: &Path, out: &Path, camera: &crate::scene::Camera, (camera_index, frame): (usize, usize), t: &Timings) -> Result<String, FitError> {
    let threads = rayon::current_num_threads();
    let (w, h) = (camera.width, camera.height);
    let camera = camera_index;
    let Timings { rows, views, sequential, together, native, enlarged, .. } = t;
    let (sequential, together, native, enlarged) = (*sequential, *together, *native, *enlarged);
    let mut md = format!(
        "## Render time per view: {} ({w} x {h}, camera {camera}, frame {frame}; {threads} threads)\n\n| light | s per view, all threads | s per view, one thread | ratio |\n|---|---|---|---|\n",
        run.display()
    );
    let mut csv_rows: Vec<[String; 3]> = Vec::new();
    for (name, all, one) in rows {
        md += &format!("| {name} | {all:.3} | {one:.3} | {:.2}x |\n", all / one);
        csv_rows.push([name.to_string(), format!("{all:.5}"), format!("{one:.5}")]);
    }
    let (lights, shared, apart) = t.lights_at_once;
    md += &format!(
        "\nThe view in those {lights} lights from one trace of its geometry, as the evaluation renders a view it has in several lights (`eval::render_view_lights`): {shared:.3} s against {apart:.3} s for the {lights} renders on their own ({:.2}x).\n",
        shared / apart
    );
    csv_rows.push([format!("{lights} lights from one trace"), format!("{shared:.5}"), String::new()]);
    csv_rows.push([format!("{lights} lights rendered apart"), format!("{apart:.5}"), String::new()]);
    md += &format!(
        "\n{} test views of the fitted light, as the evaluation renders them: {sequential:.3} s per view one after another, {together:.3} s per view {} at once ({:.2}x). Peak memory {} MiB.\n",
        views,
        views,
        together / sequential,
        peak_rss_mib().map_or("-".to_string(), |m| format!("{m:.0}"))
    );
    md += &format!(
        "\nThe view in the fitted light at {ENLARGE} times its width and height ({} x {}, `--size`): {enlarged:.3} s against {native:.3} s, {:.1}x the time for {}x the pixels.\n",
        w * ENLARGE,
        h * ENLARGE,
        enlarged / native,
        ENLARGE * ENLARGE
    );
    csv_rows.push([format!("fitted light at {ENLARGE}x the side"), format!("{enlarged:.5}"), String::new()]);
    csv_rows.push(["views one after another".into(), format!("{sequential:.5}"), String::new()]);
    csv_rows.push(["views at once".into(), format!("{together:.5}"), String::new()]);
    match t.strata {
        Some(([traced, shortcuts], strata_views)) => {
            md += &format!(
                "\nPixels rendered over their area (an area capture), {} test views with their albedos at once: {traced:.3} s per view with every stratum traced, {shortcuts:.3} s with the strata interpolated inside the body and searched near their neighbours' depths along silhouettes ({:.2}x).\n",
                strata_views,
                shortcuts / traced
            );
            csv_rows.push(["views with albedo every stratum traced".into(), format!("{traced:.5}"), String::new()]);
            csv_rows.push(["views with albedo strata shortcuts".into(), format!("{shortcuts:.5}"), String::new()]);
        }
        None => md += "\nThe capture's pixels are their centres: no pixel is rendered over its area.\n",
    }
    let csv = crate::table::to_csv(&["light", "seconds_all_threads", "seconds_one_thread"], csv_rows);
    std::fs::create_dir_all(out).map_err(|e| io(out, e))?;
    let write = |name: &str, text: &str| crate::imageio::write_atomic(&out.join(name), text.as_bytes()).map_err(|e| io(&out.join(name), e));
    write("render.md", &md)?;
    write("render.csv", &csv)?;
    let chart = BarChart {
        title: "seconds per view".into(),
        unit: "s".into(),
        labels: rows.iter().map(|r| r.0.clone()).collect(),
        series: vec![("all threads".into(), rows.iter().map(|r| r.1).collect()), ("one thread".into(), rows.iter().map(|r| r.2).collect())],
    };
    chart.render(900).save_png(&out.join("render.png")).map_err(|e| io(&out.join("render.png"), e))?;
    Ok(md)
}
