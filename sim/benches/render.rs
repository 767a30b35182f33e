//! Renderer speed: one 960x540 frame (the area pipeline's working resolution) of each
//! outdoor scenario from a mission pose. Target: at most 100 ms median on 2 cores.

use criterion::{criterion_group, criterion_main, Criterion};
use mavloc_sim::{Mission, Renderer, Scenario, World};

fn render(c: &mut Criterion) {
    for name in ["coastline", "cliff"] {
        let scenario = Scenario::load(name).unwrap();
        let world = World::build(&scenario).unwrap();
        let mission = Mission::plan(&world).unwrap();
        let renderer = Renderer::new(&world);
        let k = scenario.intrinsics().downscaled(2);
        let pose = mission.camera_pose(&mission.state(20.0));
        c.bench_function(&format!("render_960x540_{name}"), |b| b.iter(|| renderer.render(&pose, &k)));
    }
}

criterion_group! {
    name = benches;
    config = Criterion::default().sample_size(20);
    targets = render
}
criterion_main!(benches);
