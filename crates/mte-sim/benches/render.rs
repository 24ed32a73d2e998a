//! Rendering throughput: one PushT pixel observation (draw block + agent, cv2-exact bilinear
//! downscale) per iteration, cycling through a fixed set of scenes so that every frame differs
//! from the previous one, as in an episode.
//!
//! Run: `cargo bench -p mte-sim --bench render`.

use divan::{Bencher, black_box};
use mte_sim::geometry::{GOAL, Pose};
use mte_sim::render::{Renderer, Scene, resize_bilinear_u8};

fn main() {
    divan::main();
}

/// 64 scenes spread over the arena (deterministic), block and agent moving between frames.
fn scenes() -> Vec<Scene> {
    (0..64)
        .map(|i| {
            let t = i as f64;
            Scene {
                agent: [80.0 + (t * 37.0) % 350.0, 90.0 + (t * 53.0) % 330.0],
                block: Pose {
                    x: 120.0 + (t * 41.0) % 270.0,
                    y: 110.0 + (t * 29.0) % 280.0,
                    theta: t * 0.37,
                },
                goal: GOAL,
            }
        })
        .collect()
}

#[divan::bench(args = [(96, 96), (84, 84)])]
fn observation_into(bencher: Bencher, (w, h): (usize, usize)) {
    let scenes = scenes();
    let mut r = Renderer::new(GOAL);
    let mut out = vec![0u8; w * h * 3];
    let mut i = 0;
    bencher.bench_local(|| {
        i = (i + 1) % scenes.len();
        let res = r.observation_into(black_box(&scenes[i]), w, h, &mut out);
        black_box((&res, &out));
    });
}

#[divan::bench]
fn canvas_rgb(bencher: Bencher) {
    let scenes = scenes();
    let mut r = Renderer::new(GOAL);
    let mut i = 0;
    bencher.bench_local(|| {
        i = (i + 1) % scenes.len();
        black_box(r.canvas_rgb(black_box(&scenes[i])))
    });
}

#[divan::bench]
fn resize_512_to_96(bencher: Bencher) {
    let src: Vec<u8> = (0..512 * 512 * 3).map(|i| (i * 7 % 251) as u8).collect();
    let mut dst = vec![0u8; 96 * 96 * 3];
    bencher.bench_local(|| {
        let res = resize_bilinear_u8(black_box(&src), 512, 512, 3, &mut dst, 96, 96);
        black_box((&res, &dst));
    });
}

#[divan::bench]
fn visualization_680(bencher: Bencher) {
    let scenes = scenes();
    let mut r = Renderer::new(GOAL);
    let mut i = 0;
    bencher.bench_local(|| {
        i = (i + 1) % scenes.len();
        black_box(r.visualization(black_box(&scenes[i]), Some([200.0, 300.0]), 680, 680))
    });
}

#[divan::bench]
fn renderer_new(bencher: Bencher) {
    bencher.bench_local(|| black_box(Renderer::new(black_box(GOAL))));
}
