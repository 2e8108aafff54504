//! The run database on both backends: a run, its states and units written and read back, the
//! schema migrated from a database written before migrations were versioned.
//!
//! PostgreSQL: the tests marked `ignore` run against the server named by
//! `COILSCOPE_TEST_POSTGRES` (a `postgres://` URL; `.ci/run` starts one), and fail without it.

use coilscope_db::{list_runs, read_states, read_units, StateRow, Store, Target, UnitFilter};

fn round_trip(target: &Target) {
    let mut s = Store::create(target, "virtual:test", &serde_json::json!({"volts": 2.0})).unwrap();
    for k in 0..3 {
        s.push_state(StateRow {
            t: k as f64,
            stage: "large".into(),
            x_max: 1e-3 * k as f64,
            re: f64::NAN,
            ..Default::default()
        });
    }
    s.push_estimate(2.0, 0.01, &serde_json::json!({"Re": 3.1}));
    s.push_distortion(2.0, [0.1; 9], "Bl", "Kms");
    s.commit(2.0).unwrap();
    let a = s.record_unit("unit-a", true, &serde_json::json!({"Re": 3.1}), &serde_json::json!({"pass": true})).unwrap();
    let b =
        s.record_unit("unit-b", false, &serde_json::json!({"Re": 3.5}), &serde_json::json!({"pass": false})).unwrap();
    assert_eq!((a, b), (0, 1));
    s.finish::<serde_json::Value>(3.0, "finished", None).unwrap();
    let run = s.run;

    let runs = list_runs(target).unwrap();
    let r = runs.iter().find(|r| r.id == run).unwrap();
    assert_eq!((r.status.as_str(), r.states, r.estimates, r.units), ("finished", 3, 1, 2));
    assert_eq!(r.last.as_ref().unwrap().x_max, 2e-3);
    // A value not known when the state was written (NaN) reads back as NaN.
    assert!(r.last.as_ref().unwrap().re.is_nan());
    let states = read_states(target, Some(run)).unwrap();
    assert_eq!(states.iter().map(|s| s.t).collect::<Vec<_>>(), vec![0.0, 1.0, 2.0]);
    let units = read_units(target, &UnitFilter { run: Some(run), unit_id: None }).unwrap();
    assert_eq!(units.len(), 2);
    assert_eq!((units[0].unit_id.as_str(), units[0].pass, units[1].pass), ("unit-a", true, false));
    let history = read_units(target, &UnitFilter { run: None, unit_id: Some("unit-b".into()) }).unwrap();
    assert!(history.iter().all(|u| u.unit_id == "unit-b") && history.iter().any(|u| u.run == run));
}

#[test]
fn a_run_and_its_units_round_trip_on_sqlite() {
    let d = tempfile::tempdir().unwrap();
    round_trip(&Target::Sqlite(d.path().join("run.sqlite")));
    // Opened again (migrations already applied), a second run.
    round_trip(&Target::Sqlite(d.path().join("run.sqlite")));
    assert_eq!(list_runs(&Target::parse(d.path().to_str().unwrap())).unwrap().len(), 2);
}

/// A database written before the schema was versioned (the tables as they were, no
/// migration history) keeps its runs and gains the new tables.
#[test]
fn a_database_from_before_versioned_migrations_is_brought_up_to_date() {
    let d = tempfile::tempdir().unwrap();
    let path = d.path().join("run.sqlite");
    {
        let c = rusqlite::Connection::open(&path).unwrap();
        c.execute_batch(
            "CREATE TABLE runs(id INTEGER PRIMARY KEY, started REAL NOT NULL, device TEXT NOT NULL, options TEXT NOT NULL,
                 status TEXT NOT NULL, seconds REAL NOT NULL DEFAULT 0, heartbeat REAL NOT NULL, result TEXT);
             CREATE TABLE states(run INTEGER NOT NULL REFERENCES runs(id), t REAL NOT NULL, stage TEXT NOT NULL, u_rms REAL, i_rms REAL,
                 gain REAL, f_hp REAL, x_min REAL, x_max REAL, dtv REAL, re REAL, residual REAL);
             CREATE TABLE estimates(run INTEGER NOT NULL REFERENCES runs(id), t REAL NOT NULL, residual REAL, parameters TEXT NOT NULL);
             CREATE TABLE distortion(run INTEGER NOT NULL REFERENCES runs(id), t REAL NOT NULL, bl_x REAL, kms_x REAL, le_x REAL,
                 bl_i REAL, kms_i REAL, le_i REAL, bl_p REAL, kms_p REAL, le_p REAL, dominant_x TEXT, dominant_p TEXT);
             INSERT INTO runs(started, device, options, status, seconds, heartbeat) VALUES (1.0, 'virtual:old', '{}', 'converged', 42.0, 1.0);
             INSERT INTO states(run, t, stage) VALUES (1, 0.5, 'small');",
        )
        .unwrap();
    }
    let target = Target::Sqlite(path);
    let runs = list_runs(&target).unwrap();
    assert_eq!(
        (runs.len(), runs[0].device.as_str(), runs[0].status.as_str(), runs[0].states),
        (1, "virtual:old", "converged", 1)
    );
    round_trip(&target);
}

#[test]
fn a_missing_database_file_is_named_not_created() {
    let d = tempfile::tempdir().unwrap();
    let path = d.path().join("nowhere.sqlite");
    let e = list_runs(&Target::Sqlite(path.clone())).unwrap_err();
    assert!(e.contains("nowhere.sqlite") && e.contains("no such run database"), "{e}");
    assert!(!path.exists());
}

#[test]
fn a_file_that_is_not_a_database_is_refused_with_its_name() {
    let d = tempfile::tempdir().unwrap();
    let path = d.path().join("notes.sqlite");
    std::fs::write(&path, "these are not the runs you are looking for, but a text file of some length ........")
        .unwrap();
    let e = list_runs(&Target::Sqlite(path)).unwrap_err();
    assert!(e.contains("notes.sqlite") && e.contains("not a coilscope run database"), "{e}");
}

/// The server `.ci/run` starts (`COILSCOPE_TEST_POSTGRES`).
fn postgres_url() -> String {
    std::env::var("COILSCOPE_TEST_POSTGRES").expect(
        "COILSCOPE_TEST_POSTGRES=postgres://USER@HOST:PORT/DATABASE: the PostgreSQL server of this test (.ci/run starts one)",
    )
}

#[test]
#[ignore = "needs a PostgreSQL server: COILSCOPE_TEST_POSTGRES=postgres://... cargo test --release -p coilscope-db -- --ignored"]
fn a_run_and_its_units_round_trip_on_postgres() {
    let target = Target::parse(&postgres_url());
    round_trip(&target);
    round_trip(&target);
}

#[test]
fn an_unreachable_server_is_named_without_its_password() {
    let e = match Store::create(&Target::parse("postgres://line:secret@127.0.0.1:9/none"), "x", &serde_json::json!({}))
    {
        Err(e) => e,
        Ok(_) => panic!("a server on port 9"),
    };
    assert!(e.contains("postgres://line:***@127.0.0.1:9/none") && !e.contains("secret"), "{e}");
    assert!(e.contains("cannot connect"), "{e}");
}
