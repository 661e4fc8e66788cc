//! The lift-safety interlock (docs/GATEWAY.md §Lift-safety interlock), against the simulated
//! lift through portal and gateway: in fire service and in inspection a passenger call is
//! refused with 08000022h and audited as refused while reads go on; back in normal operation the
//! same call is taken and the car travels.

use serde_json::{json, Value};
use testkit::constants::{LIFT, WAIT};
use testkit::portal::{until, Rig};

async fn until_state(rig: &Rig, state: &str) {
    until(WAIT, &format!("lift state {state}"), || async {
        rig.naked("0x502400").await == state
    })
    .await;
}

async fn call_car(rig: &Rig, floor: u8) -> (u16, Value) {
    let path = format!("/api/v1/lifts/{LIFT}/objects/0x502200");
    let body = json!({"value": floor.to_string(), "datatype": 7, "physunit": 0});
    rig.call("PUT", &path, Some(&rig.key), Some(body)).await
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_passenger_call_is_refused_in_fire_service_and_inspection_and_taken_after() {
    let rig = Rig::builder()
        .sim(|s| s.faults = lift417::sim::FIRE_SERVICE)
        .start()
        .await;
    rig.online().await;
    until_state(&rig, "6").await;
    let (status, refused) = call_car(&rig, 4).await;
    assert_eq!(
        (status, &refused["code"]),
        (403, &json!(0x0800_0022)),
        "{refused}"
    );
    assert!(
        refused["message"]
            .as_str()
            .unwrap()
            .contains("present device state"),
        "{refused}"
    );
    // Reads go on, and the car stays where fire service recalled it.
    assert_eq!(rig.naked("0x502300").await, "1");

    // Inspection, the same.
    rig.sim().set_switches(1, lift417::sim::INSPECTION);
    until_state(&rig, "8").await;
    assert_eq!(call_car(&rig, 5).await.1["code"], json!(0x0800_0022));

    // Normal operation: the call is taken and the car travels to floor 4.
    rig.sim().set_switches(1, 0);
    until(WAIT, "the lift back in normal operation", || async {
        !["6", "7", "8", "4"].contains(&rig.naked("0x502400").await.as_str().unwrap_or(""))
    })
    .await;
    let (status, body) = call_car(&rig, 4).await;
    assert_eq!(status, 200, "{body}");
    until(WAIT * 2, "the car at floor 4", || async {
        rig.naked("0x502300").await == "4"
    })
    .await;

    // The audit has the two refusals with their code and the call taken.
    let (_, audit) = rig.call("GET", "/api/v1/audit", Some(&rig.key), None).await;
    let results: Vec<&str> = audit
        .as_array()
        .unwrap()
        .iter()
        .filter(|e| e["object"] == "0x502200")
        .map(|e| e["result"].as_str().unwrap_or_default())
        .collect();
    assert_eq!(results.len(), 3, "{audit}");
    assert_eq!(results[0], "ok", "newest first: {results:?}");
    let refused = format!("error {}", 0x0800_0022);
    assert_eq!(results[1..], [refused.as_str(), refused.as_str()]);
    rig.stop().await;
}
