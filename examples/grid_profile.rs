//! Where a grid lookup's time goes: planning on the CPU, the tensor gather and its backward,
//! for one training step's worth of sample points (512 rays x 24 samples), and the untracked
//! lookup of a ray's search for the body.
use burn::module::Module;
use burn::tensor::{Device, Tensor, TensorData};
use glam::DVec3;
use std::time::Instant;
use umbra::field::grid::lookup;
use umbra::field::{FieldConfig, PoseTensors};
use umbra::random::Stream;
use umbra::synth::character::{Character, Kind};

fn main() {
    let character = Character::new(Kind::Human);
    let pose = character.pose(0.3, 0.0, DVec3::ZERO);
    let (lo, hi) = pose.bounds(&character.skeleton);
    let config = FieldConfig::with_grid(character.skeleton.bones.iter().map(|b| b.length as f32).collect(), (hi - lo).length() as f32);
    let grid = config.grid.clone().unwrap();
    let levels = grid.layout();
    let device = Device::flex().autodiff();
    let tensors = PoseTensors::new(&pose, &character.skeleton, &device);
    let mut s = Stream::new(1, 2, 3);
    let n = 512 * 24;
    let points: Vec<f32> = (0..n * 3).map(|k| (lo[k % 3] + (hi[k % 3] - lo[k % 3]) * s.uniform()) as f32).collect();
    let skinning = config.skinning();
    let repeat = 10;
    let t = Instant::now();
    for _ in 0..repeat {
        std::hint::black_box(lookup(&grid, &levels, &tensors.frames, skinning, &points, false));
    }
    println!("plan: {:.1} ms", t.elapsed().as_secs_f64() * 1e3 / repeat as f64);
    let t = Instant::now();
    for _ in 0..repeat {
        std::hint::black_box(lookup(&grid, &levels, &tensors.frames, skinning, &points, true));
    }
    println!("plan with tangents: {:.1} ms", t.elapsed().as_secs_f64() * 1e3 / repeat as f64);
    let t = Instant::now();
    for _ in 0..repeat {
        std::hint::black_box(umbra::field::grid::lookup_carried(&grid, &levels, &tensors.frames, skinning, &points));
    }
    println!("plan for a carried shift (cells' fractions): {:.1} ms", t.elapsed().as_secs_f64() * 1e3 / repeat as f64);
    let field = config.init(&device, 0);
    let input = Tensor::<2>::from_data(TensorData::new(points.clone(), [n, 3]), &device);
    // Where no gradient is wanted (an untracked table: a ray's search for the body) the lookup
    // is planned and summed in one pass on the host; the fastest of several rounds.
    let still = field.valid();
    let still_input = input.clone().inner();
    let fastest = (0..5)
        .map(|_| {
            let t = Instant::now();
            for _ in 0..repeat {
                std::hint::black_box(still.grid.as_ref().unwrap().encode(still_input.clone(), &tensors.frames, skinning, false, None).features.into_data());
            }
            t.elapsed().as_secs_f64() * 1e3 / repeat as f64
        })
        .fold(f64::INFINITY, f64::min);
    println!("untracked lookup (one pass on the host): {fastest:.1} ms");
    for (name, composite) in [("fused op", false), ("composite of tensor ops", true)] {
        let mut grid = field.grid.clone().unwrap();
        grid.route = if composite { umbra::field::grid::Route::Composite } else { umbra::field::grid::Route::Fused };
        let encode = |tangents: bool| grid.encode(input.clone(), &tensors.frames, skinning, tangents, None);
        let t = Instant::now();
        for _ in 0..repeat {
            std::hint::black_box(encode(false).features.into_data());
        }
        println!("{name}: encode forward: {:.1} ms", t.elapsed().as_secs_f64() * 1e3 / repeat as f64);
        for tangents in [false, true] {
            let t = Instant::now();
            for _ in 0..repeat {
                let f = encode(tangents);
                let mut loss = f.features.sum();
                if let Some((d, _)) = f.tangents {
                    loss = loss + d.sum();
                }
                let g = loss.backward();
                std::hint::black_box(grid.table.grad(&g));
            }
            println!(
                "{name}: encode forward + backward{}: {:.1} ms",
                if tangents { " with tangents" } else { "" },
                t.elapsed().as_secs_f64() * 1e3 / repeat as f64
            );
        }
    }
    // A training step's lookup while the motion is refined: it carries a motion increment.
    let mut moving = PoseTensors::new(&pose, &character.skeleton, &device);
    moving.motion = Some(umbra::skeleton::MotionIncrement::new(&character.skeleton, &pose, &device));
    let grid = field.grid.clone().unwrap();
    let t = Instant::now();
    for _ in 0..repeat {
        let f = grid.encode(input.clone(), &moving.frames, skinning, false, moving.motion.as_ref());
        let g = (f.features.sum() + f.prior.sum()).backward();
        std::hint::black_box(grid.table.grad(&g));
    }
    println!("fused op carrying a motion increment: encode forward + backward: {:.1} ms", t.elapsed().as_secs_f64() * 1e3 / repeat as f64);
    let t = Instant::now();
    for _ in 0..repeat {
        let out = field.forward(input.clone(), &tensors);
        let g = (out.sdf.sum() + out.albedo.sum()).backward();
        std::hint::black_box(field.grid.as_ref().unwrap().table.grad(&g));
    }
    println!("field forward + backward: {:.1} ms", t.elapsed().as_secs_f64() * 1e3 / repeat as f64);
    let mlp = FieldConfig::for_bones(character.skeleton.len()).init(&device, 0);
    let t = Instant::now();
    for _ in 0..repeat {
        let out = mlp.forward(input.clone(), &tensors);
        let g = (out.sdf.sum() + out.albedo.sum()).backward();
        std::hint::black_box(mlp.output.weight.grad(&g));
    }
    println!("mlp field forward + backward: {:.1} ms", t.elapsed().as_secs_f64() * 1e3 / repeat as f64);
}
