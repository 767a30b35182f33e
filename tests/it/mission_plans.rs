//! The committed QGroundControl plans in `mission/` are what the scenarios generate.

use mavloc_sim::{Mission, Scenario, World};

#[test]
fn committed_plans_match_the_scenarios() {
    for name in ["coastline", "cliff", "indoor-floor"] {
        let scenario = Scenario::load(name).unwrap();
        let world = World::build(&scenario).unwrap();
        let mission = Mission::plan(&world).unwrap();
        let generated: serde_json::Value = serde_json::to_value(mission.qgc_plan(&world.frame)).unwrap();
        let path = format!("{}/mission/{name}.plan", env!("CARGO_MANIFEST_DIR"));
        let committed: serde_json::Value =
            serde_json::from_str(&std::fs::read_to_string(&path).unwrap()).unwrap();
        assert_eq!(
            committed, generated,
            "{path} is stale: run `mavloc sim plan --scenario {name} --out mission/{name}.plan`"
        );
    }
}
