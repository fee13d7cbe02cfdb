//! The behaviour every [`JobRepo`] owes, as one suite: [`run`] takes a [`Backend`] (a way
//! to make an empty database and open handles on it, and the clock its leases run out in)
//! and runs every check on a database of its own. SQLite's unit tests run it on a file;
//! `tests/backends/postgres.rs` runs it on a real PostgreSQL server. A check that only one backend
//! can make (SQLite's upgrade of an old file, PostgreSQL's unreachable server) stays with
//! that backend.

use std::cell::Cell;
use std::collections::HashSet;
use std::sync::Arc;
use std::time::{Duration, SystemTime, UNIX_EPOCH};

use uuid::Uuid;

use super::{
    Admission, ArtifactInfo, CalibrationRecord, Finish, JobRecord, JobRepo, JobStatus, Lease,
    Problem, Reaped, Remembered,
};

/// A backend under test.
pub trait Backend {
    /// A database of its own for one check.
    type Db;
    /// A new, empty database for the check named `check`.
    fn create(&self, check: &str) -> Self::Db;
    /// A handle on `db`, opened (and migrated) as a start opens it.
    fn open(&self, db: &Self::Db) -> Arc<dyn JobRepo>;
    /// `n` handles on `db`, as `n` instances that start together open them.
    fn open_many(&self, db: &Self::Db, n: usize) -> Vec<Arc<dyn JobRepo>> {
        (0..n).map(|_| self.open(db)).collect()
    }
    /// The clock its leases run out in.
    fn clock(&self) -> Clock;
}

/// The clock a backend's leases run out in, and how a check lets time pass.
pub enum Clock {
    /// The callers' `now` (SQLite): time is what the check says it is, so a lease's end
    /// is checked to the millisecond.
    Given(Cell<i64>),
    /// The database's own (PostgreSQL): the check waits, with a margin for the time its
    /// calls take.
    Wall,
}

impl Clock {
    /// A clock that starts at `at` and moves only when told.
    pub fn given(at: i64) -> Self {
        Clock::Given(Cell::new(at))
    }

    /// Milliseconds since the Unix epoch, to pass as `now`.
    fn now(&self) -> i64 {
        match self {
            Clock::Given(now) => now.get(),
            Clock::Wall => SystemTime::now()
                .duration_since(UNIX_EPOCH)
                .map_or(0, |d| d.as_millis() as i64),
        }
    }

    /// Let time pass until `at`.
    fn wait_until(&self, at: i64) {
        match self {
            Clock::Given(now) => now.set(now.get().max(at)),
            Clock::Wall => {
                let left = at - self.now();
                if left > 0 {
                    std::thread::sleep(Duration::from_millis(left as u64));
                }
            }
        }
    }

    /// A lease long enough to check both sides of its end.
    fn lease(&self) -> Duration {
        match self {
            Clock::Given(_) => Duration::from_secs(5),
            Clock::Wall => Duration::from_millis(1500),
        }
    }

    /// How close to a lease's end a check may come and still know which side it is on.
    fn margin(&self) -> i64 {
        match self {
            Clock::Given(_) => 1,
            Clock::Wall => 400,
        }
    }
}

/// One check of the contract, on a database of its own.
type Check<B> = fn(&B, &<B as Backend>::Db);

/// Run every check, each on a database of its own (its name is printed first, so a
/// failure says which).
pub fn run<B: Backend>(backend: &B) {
    let checks: [(&str, Check<B>); 12] = [
        ("records_and_state_rules", records_and_state_rules::<B>),
        ("lifecycle_and_races", lifecycle_and_races::<B>),
        ("tenants_take_turns", tenants_take_turns::<B>),
        ("admission_limits", admission_limits::<B>),
        ("paging", paging::<B>),
        ("reopening", reopening::<B>),
        ("calibrations", calibrations::<B>),
        ("idempotent_answers", idempotent_answers::<B>),
        ("claims_are_exclusive", claims_are_exclusive::<B>),
        ("leases_fence_late_writers", leases_fence_late_writers::<B>),
        ("last_attempt_fails", last_attempt_fails::<B>),
        (
            "first_attempt_fails_at_one",
            first_attempt_fails_at_one::<B>,
        ),
    ];
    for (name, check) in checks {
        eprintln!("repo contract: {name}");
        let db = backend.create(name);
        check(backend, &db);
    }
}

/// A queued job of `tenant`, created at `created_at`.
fn job(tenant: &str, created_at: i64) -> JobRecord {
    JobRecord::new_queued(
        Uuid::new_v4(),
        tenant,
        created_at,
        4,
        serde_json::json!({"solver": "robust"}),
    )
}

fn accepted(repo: &dyn JobRepo, job: &JobRecord, max_active: usize) -> bool {
    repo.insert(job, max_active, 100).unwrap() == Admission::Accepted
}

/// Record a job of `tenant` at `at`.
fn queue(repo: &dyn JobRepo, tenant: &str, at: i64) -> Uuid {
    let id = Uuid::new_v4();
    let job = JobRecord::new_queued(id, tenant, at, 3, serde_json::json!({}));
    assert_eq!(repo.insert(&job, 100, 100).unwrap(), Admission::Accepted);
    id
}

/// A claim with a 5 s lease.
fn claim(repo: &dyn JobRepo, now: i64) -> Option<Lease> {
    repo.claim("w", Duration::from_secs(5), now).unwrap()
}

/// What the reaper writes for a job whose lease ran out on its last attempt.
fn lost(id: Uuid) -> Problem {
    Problem {
        kind: "urn:photostereo:problem:job-failed".into(),
        title: "Job failed".into(),
        status: 500,
        detail: format!("{id}: its worker stopped answering"),
        instance: None,
    }
}

fn succeeded(width: u32) -> Finish {
    Finish::Succeeded {
        result: serde_json::json!({ "width": width }),
        artifacts: vec![],
    }
}

/// Admission, the lifecycle, requeue against cancel, counts, paging, expiry, idempotent
/// answers and calibrations, in one sequence: every state change is conditional on the
/// state it leaves.
fn records_and_state_rules<B: Backend>(backend: &B, db: &B::Db) {
    const LEASE: Duration = Duration::from_secs(30);
    let repo = backend.open(db);
    let repo = &*repo;
    let claim = |repo: &dyn JobRepo, now| repo.claim("test", LEASE, now).unwrap();

    // Admission per tenant: at most `max_active` queued or running; at most
    // `max_queued` waiting in all.
    let a = job("acme", 1_000);
    assert!(accepted(repo, &a, 2));
    assert!(accepted(repo, &job("acme", 1_001), 2));
    assert_eq!(
        repo.insert(&job("acme", 1_002), 2, 100).unwrap(),
        Admission::TenantFull,
        "third active job refused"
    );
    assert_eq!(
        repo.insert(&job("other", 1_002), 2, 2).unwrap(),
        Admission::QueueFull
    );
    assert!(accepted(repo, &job("other", 1_003), 2));
    assert_eq!(repo.active("acme").unwrap(), 2);
    assert_eq!(repo.queued().unwrap(), 3);

    // Lifecycle: claimed once (the oldest job), progress, heartbeat, finish once.
    assert_eq!(repo.get(a.id).unwrap().unwrap().status, JobStatus::Queued);
    let lease = claim(repo, 2_000).unwrap();
    assert_eq!(lease.id, a.id);
    repo.cancel(
        claim(repo, 2_001).expect("the other tenant's turn").id,
        2_001,
    )
    .unwrap();
    assert!(repo.progress(lease, "solve", 0.25, 2_100).unwrap());
    assert!(repo.heartbeat(&[lease], LEASE, 2_200).unwrap().is_empty());
    let rec = repo.get(a.id).unwrap().unwrap();
    assert_eq!(
        (rec.status, rec.stage.as_deref(), rec.progress, rec.attempts),
        (JobStatus::Running, Some("solve"), 0.25, 1)
    );
    assert_eq!(rec.heartbeat_at, Some(2_200));
    let artifacts = vec![ArtifactInfo {
        name: "normal.png".into(),
        bytes: 1234,
        etag: "\"e\"".into(),
        key: Some("attempt-1/normal.png".into()),
    }];
    let done = Finish::Succeeded {
        result: serde_json::json!({"width": 4}),
        artifacts: artifacts.clone(),
    };
    assert!(repo.finish(lease, &done, 3_000).unwrap());
    assert!(!repo.finish(lease, &done, 3_001).unwrap(), "finished once");
    let rec = repo.get(a.id).unwrap().unwrap();
    assert_eq!(rec.status, JobStatus::Succeeded);
    assert_eq!(rec.artifacts, artifacts);
    assert_eq!(rec.result, Some(serde_json::json!({"width": 4})));
    assert_eq!(repo.stored_bytes("acme").unwrap(), 1234);
    assert_eq!(repo.stored_bytes("other").unwrap(), 0);
    assert_eq!(
        repo.cancel(a.id, 3_100).unwrap(),
        None,
        "a finished job stays"
    );

    // Requeue and cancel race: whichever comes first wins.
    let b = job("other", 1_004);
    assert!(accepted(repo, &b, 5));
    let acme_left = claim(repo, 4_000).unwrap();
    assert_ne!(acme_left.id, b.id, "acme's turn");
    repo.cancel(acme_left.id, 4_000).unwrap();
    let lease = claim(repo, 4_000).unwrap();
    assert_eq!(lease.id, b.id);
    assert!(repo.requeue(lease).unwrap());
    assert!(
        !repo.requeue(lease).unwrap(),
        "only a running job is requeued"
    );
    assert_eq!(repo.cancel(b.id, 4_100).unwrap(), Some(JobStatus::Queued));
    assert_eq!(claim(repo, 4_200), None, "a cancelled job never starts");
    let failed = job("other", 1_005);
    assert!(accepted(repo, &failed, 5));
    let problem = Problem {
        kind: "urn:photostereo:problem:invalid-input".into(),
        title: "Invalid input".into(),
        status: 422,
        detail: "three lights or more".into(),
        instance: None,
    };
    assert!(repo.fail_queued(failed.id, &problem, 4_300).unwrap());
    assert_eq!(repo.get(failed.id).unwrap().unwrap().error, Some(problem));

    // Counts, paging (newest first, from a cursor) and expiry.
    let counts = repo.counts().unwrap();
    let n = |s| counts.iter().find(|(k, _)| *k == s).unwrap().1;
    assert_eq!(
        (
            n(JobStatus::Queued),
            n(JobStatus::Succeeded),
            n(JobStatus::Cancelled)
        ),
        (0, 1, 3)
    );
    let page = repo.list(None, 3, None).unwrap();
    let times: Vec<i64> = page.iter().map(|j| j.created_at).collect();
    assert_eq!(times, vec![1_005, 1_004, 1_003]);
    let last = page.last().unwrap();
    let next = repo
        .list(None, 10, Some((last.created_at, last.id)))
        .unwrap();
    assert_eq!(next.len(), 2);
    assert!(next.iter().all(|j| j.created_at < 1_003));
    assert_eq!(repo.list(Some("acme"), 10, None).unwrap().len(), 2);
    assert_eq!(repo.unfinished().unwrap().len(), 0);
    let expired = repo.expired(5_000, 10).unwrap();
    assert_eq!(
        expired.len(),
        5,
        "succeeded, cancelled and failed jobs expire"
    );
    assert!(repo.delete(a.id).unwrap());
    assert!(repo.get(a.id).unwrap().is_none());
    assert_eq!(repo.ids().unwrap().len(), 4);

    // Idempotent answers: the first within the window is kept.
    let answer = |body: &str| Remembered {
        body_hash: "h".into(),
        status: 202,
        body: body.into(),
        location: Some("/v1/jobs/x".into()),
        created_at: 6_000,
    };
    assert_eq!(
        repo.remember("acme", "jobs", "k", &answer("one"), 0)
            .unwrap(),
        None
    );
    assert_eq!(
        repo.remember("acme", "jobs", "k", &answer("two"), 0)
            .unwrap(),
        Some(answer("one"))
    );
    assert_eq!(
        repo.idempotent("acme", "jobs", "k", 0).unwrap(),
        Some(answer("one"))
    );
    assert_eq!(repo.idempotent("other", "jobs", "k", 0).unwrap(), None);
    assert_eq!(repo.forget_idempotent(7_000).unwrap(), 1);

    // Calibrations.
    let cal = CalibrationRecord {
        id: Uuid::new_v4(),
        tenant: "acme".into(),
        created_at: 8_000,
        detail: serde_json::json!({"lights": 3}),
        table: "0 0 1\n".into(),
        artifacts: vec![],
    };
    repo.insert_calibration(&cal).unwrap();
    assert_eq!(repo.get_calibration(cal.id).unwrap(), Some(cal.clone()));
    assert_eq!(
        repo.list_calibrations(Some("acme"), 5, None).unwrap(),
        vec![cal.clone()]
    );
    assert!(
        repo.list_calibrations(Some("other"), 5, None)
            .unwrap()
            .is_empty()
    );
    assert_eq!(repo.calibration_ids().unwrap(), vec![cal.id]);
    assert!(repo.delete_calibration(cal.id).unwrap());
    repo.ping().unwrap();
}

/// Tenants take turns at the queue, and each tenant's jobs keep their order.
fn tenants_take_turns<B: Backend>(backend: &B, db: &B::Db) {
    let repo = backend.open(db);
    let repo = &*repo;
    let a: Vec<Uuid> = (0..4).map(|i| queue(repo, "a", i)).collect();
    let b: Vec<Uuid> = (0..2).map(|i| queue(repo, "b", 10 + i)).collect();
    let order: Vec<Uuid> = (0..6).map(|i| claim(repo, 100 + i).unwrap().id).collect();
    assert_eq!(order, [a[0], b[0], a[1], b[1], a[2], a[3]]);
}

/// Claimed once, cancelled while running: the cancel wins over the finish, and the
/// lease is no longer held.
fn lifecycle_and_races<B: Backend>(backend: &B, db: &B::Db) {
    let repo = backend.open(db);
    let repo = &*repo;
    let id = Uuid::new_v4();
    assert_eq!(
        repo.insert(
            &JobRecord::new_queued(id, "t", 1000, 4, serde_json::json!({})),
            9,
            9
        )
        .unwrap(),
        Admission::Accepted
    );
    let lease = claim(repo, 2000).unwrap();
    assert_eq!(lease.id, id);
    assert!(claim(repo, 2001).is_none(), "only a queued job is claimed");
    assert!(repo.progress(lease, "solve", 0.25, 2100).unwrap());
    let rec = repo.get(id).unwrap().unwrap();
    assert_eq!(rec.status, JobStatus::Running);
    assert_eq!(rec.stage.as_deref(), Some("solve"));
    assert_eq!(rec.attempts, 1);
    assert_eq!(repo.cancel(id, 2200).unwrap(), Some(JobStatus::Running));
    assert_eq!(
        repo.heartbeat(&[lease], Duration::from_secs(5), 2250)
            .unwrap(),
        [lease],
        "a cancelled job's lease is no longer held"
    );
    let done = Finish::Succeeded {
        result: serde_json::json!({"width": 3}),
        artifacts: vec![],
    };
    assert!(!repo.finish(lease, &done, 2300).unwrap(), "cancel wins");
    assert_eq!(repo.cancel(id, 2400).unwrap(), None);
    assert_eq!(repo.get(id).unwrap().unwrap().status, JobStatus::Cancelled);
    assert_eq!(repo.expired(2201, 10).unwrap(), vec![id]);
    assert!(repo.delete(id).unwrap());
    assert!(repo.get(id).unwrap().is_none());
}

/// Pages are newest first and stable (the id breaks ties), of all tenants or one.
fn paging<B: Backend>(backend: &B, db: &B::Db) {
    let repo = backend.open(db);
    let repo = &*repo;
    let mut ids = Vec::new();
    for i in 0..7 {
        let id = Uuid::new_v4();
        // Two jobs per millisecond: the id breaks ties.
        repo.insert(
            &JobRecord::new_queued(
                id,
                if i % 3 == 0 { "a" } else { "b" },
                100 + i / 2,
                3,
                serde_json::json!({}),
            ),
            100,
            100,
        )
        .unwrap();
        ids.push(id);
    }
    let mut seen = Vec::new();
    let mut cursor = None;
    loop {
        let page = repo.list(None, 3, cursor).unwrap();
        if page.is_empty() {
            break;
        }
        cursor = page.last().map(|r| (r.created_at, r.id));
        seen.extend(page);
    }
    assert_eq!(seen.len(), 7);
    assert!(
        seen.windows(2)
            .all(|w| (w[0].created_at, w[0].id) > (w[1].created_at, w[1].id))
    );
    let counts = repo.counts().unwrap();
    assert_eq!(counts[0], (JobStatus::Queued, 7));
    // One tenant's pages hold only its jobs, in the same order.
    let a = repo.list(Some("a"), 2, None).unwrap();
    let rest = repo
        .list(Some("a"), 2, a.last().map(|r| (r.created_at, r.id)))
        .unwrap();
    let theirs: Vec<Uuid> = seen
        .iter()
        .filter(|r| r.tenant == "a")
        .map(|r| r.id)
        .collect();
    let paged: Vec<Uuid> = a.iter().chain(&rest).map(|r| r.id).collect();
    assert_eq!(paged, theirs);
    assert_eq!(theirs.len(), 3);
}

/// A tenant past its active jobs, or a full queue, is refused; a finished job no longer
/// counts, but its artifacts are stored bytes.
fn admission_limits<B: Backend>(backend: &B, db: &B::Db) {
    let repo = backend.open(db);
    let repo = &*repo;
    // Created in the order made, so that the first one is claimed first.
    let clock = std::cell::Cell::new(0);
    let job = |t: &str| {
        clock.set(clock.get() + 1);
        JobRecord::new_queued(Uuid::new_v4(), t, clock.get(), 1, serde_json::json!({}))
    };
    let (first, second) = (job("a"), job("a"));
    let accepted = |j: &JobRecord| repo.insert(j, 2, 4).unwrap() == Admission::Accepted;
    assert!(accepted(&first));
    assert!(accepted(&second));
    assert_eq!(
        repo.insert(&job("a"), 2, 4).unwrap(),
        Admission::TenantFull,
        "a has 2 active"
    );
    assert!(accepted(&job("b")), "b is not counted with a");
    assert_eq!(repo.active("a").unwrap(), 2);
    assert_eq!(repo.queued().unwrap(), 3);
    assert_eq!(
        repo.insert(&job("c"), 2, 3).unwrap(),
        Admission::QueueFull,
        "3 wait"
    );
    // A finished job no longer counts, but its artifacts are stored bytes.
    let first = claim(repo, 2).unwrap();
    assert_eq!(repo.queued().unwrap(), 2);
    assert_eq!(repo.get(first.id).unwrap().unwrap().tenant, "a");
    let artifact = |name: &str, bytes| ArtifactInfo {
        name: name.into(),
        bytes,
        etag: "\"x\"".into(),
        key: None,
    };
    let done = Finish::Succeeded {
        result: serde_json::json!({}),
        artifacts: vec![artifact("albedo.png", 1000), artifact("mesh.glb", 234)],
    };
    assert!(repo.finish(first, &done, 3).unwrap());
    assert_eq!(repo.active("a").unwrap(), 1);
    assert!(accepted(&job("a")));
    assert_eq!(repo.stored_bytes("a").unwrap(), 1234);
    assert_eq!(repo.stored_bytes("b").unwrap(), 0);
    let by_tenant = repo.counts_by_tenant().unwrap();
    assert!(by_tenant.contains(&("a".into(), JobStatus::Queued, 2)));
    assert!(by_tenant.contains(&("a".into(), JobStatus::Succeeded, 1)));
    assert!(by_tenant.contains(&("b".into(), JobStatus::Queued, 1)));
}

/// Calibrations are kept, listed per tenant and deleted; jobs and calibrations do not meet.
fn calibrations<B: Backend>(backend: &B, db: &B::Db) {
    let repo = backend.open(db);
    let repo = &*repo;
    let cal = |tenant: &str, at| CalibrationRecord {
        id: Uuid::new_v4(),
        tenant: tenant.into(),
        created_at: at,
        detail: serde_json::json!({"image_count": 3}),
        table: "im1.png, 0, 0, 1\n".into(),
        artifacts: vec![ArtifactInfo {
            name: "lights.csv".into(),
            bytes: 17,
            etag: "\"x\"".into(),
            key: None,
        }],
    };
    let (a1, b1, a2) = (cal("a", 10), cal("b", 11), cal("a", 12));
    for c in [&a1, &b1, &a2] {
        repo.insert_calibration(c).unwrap();
    }
    assert_eq!(repo.get_calibration(a1.id).unwrap().as_ref(), Some(&a1));
    let ids = |page: Vec<CalibrationRecord>| page.into_iter().map(|c| c.id).collect::<Vec<_>>();
    assert_eq!(
        ids(repo.list_calibrations(Some("a"), 10, None).unwrap()),
        [a2.id, a1.id]
    );
    assert_eq!(
        ids(repo.list_calibrations(None, 2, Some((12, a2.id))).unwrap()),
        [b1.id, a1.id]
    );
    assert_eq!(repo.calibration_ids().unwrap().len(), 3);
    assert!(repo.delete_calibration(a1.id).unwrap());
    assert!(!repo.delete_calibration(a1.id).unwrap());
    assert!(repo.get_calibration(a1.id).unwrap().is_none());
    // Jobs and calibrations do not meet.
    assert!(repo.get(b1.id).unwrap().is_none());
}

/// Idempotent answers are kept per tenant, scope and key for the window; the first one
/// stays.
fn idempotent_answers<B: Backend>(backend: &B, db: &B::Db) {
    let repo = backend.open(db);
    let repo = &*repo;
    let answer = |hash: &str, at| Remembered {
        body_hash: hash.into(),
        status: 202,
        body: format!("{{\"h\":\"{hash}\"}}"),
        location: Some("/v1/jobs/x".into()),
        created_at: at,
    };
    let first = answer("h1", 100);
    assert_eq!(repo.remember("a", "jobs", "k", &first, 0).unwrap(), None);
    // A second answer for the same key does not replace the first.
    assert_eq!(
        repo.remember("a", "jobs", "k", &answer("h2", 150), 0)
            .unwrap(),
        Some(first.clone())
    );
    assert_eq!(
        repo.idempotent("a", "jobs", "k", 0).unwrap(),
        Some(first.clone())
    );
    assert_eq!(repo.idempotent("b", "jobs", "k", 0).unwrap(), None);
    assert_eq!(repo.idempotent("a", "calibrations", "k", 0).unwrap(), None);
    // Past the window the key is free again.
    assert_eq!(repo.idempotent("a", "jobs", "k", 101).unwrap(), None);
    let later = answer("h3", 300);
    assert_eq!(repo.remember("a", "jobs", "k", &later, 101).unwrap(), None);
    assert_eq!(repo.idempotent("a", "jobs", "k", 101).unwrap(), Some(later));
    assert_eq!(repo.forget_idempotent(301).unwrap(), 1);
    assert_eq!(repo.idempotent("a", "jobs", "k", 0).unwrap(), None);
}

/// A handle opened again finds the records (and the schema) as they were.
fn reopening<B: Backend>(backend: &B, db: &B::Db) {
    let id = Uuid::new_v4();
    {
        let repo = backend.open(db);
        repo.insert(
            &JobRecord::new_queued(id, "t", 5, 3, serde_json::json!({"solver": "l2"})),
            100,
            100,
        )
        .unwrap();
    }
    let repo = backend.open(db);
    let rec = repo.get(id).unwrap().unwrap();
    assert_eq!(rec.options, serde_json::json!({"solver": "l2"}));
    assert_eq!(repo.unfinished().unwrap().len(), 1);
}

/// Instances share a database: several open it at once, and claims from many threads
/// over several handles each get a job of their own.
fn claims_are_exclusive<B: Backend>(backend: &B, db: &B::Db) {
    const LEASE: Duration = Duration::from_secs(30);
    let repos = backend.open_many(db, 4);
    for i in 0..40 {
        assert!(accepted(
            &*repos[0],
            &job(["a", "b", "c"][i % 3], i as i64),
            100
        ));
    }
    let claimed: Vec<Uuid> = std::thread::scope(|s| {
        let workers: Vec<_> = (0..8)
            .map(|w| {
                let repo = repos[w % 4].clone();
                s.spawn(move || {
                    let mut mine = Vec::new();
                    while let Some(l) = repo.claim(&format!("w{w}"), LEASE, 100).unwrap() {
                        mine.push(l.id);
                    }
                    mine
                })
            })
            .collect();
        workers
            .into_iter()
            .flat_map(|h| h.join().unwrap())
            .collect()
    });
    assert_eq!(claimed.len(), 40);
    assert_eq!(
        claimed.iter().collect::<HashSet<_>>().len(),
        40,
        "claimed twice"
    );
}

/// A lease runs out in the backend's clock (to the millisecond where the callers' `now`
/// is the clock) and a heartbeat extends it; the job goes back to the queue, another
/// instance takes it over, every write of the worker that lost it is refused, and the
/// one that took over finishes it, once. A handle opened again sees the attempts.
fn leases_fence_late_writers<B: Backend>(backend: &B, db: &B::Db) {
    let clock = backend.clock();
    let (lease, margin) = (clock.lease(), clock.margin());
    let l = lease.as_millis() as i64;
    let repos = backend.open_many(db, 4);
    let id = queue(&*repos[0], "t", 1);
    let t0 = clock.now();
    let first = repos[0].claim("dies", lease, t0).unwrap().unwrap();
    assert_eq!(first.id, id);
    clock.wait_until(t0 + l - margin);
    assert_eq!(
        repos[1].reap(2, &lost, clock.now()).unwrap(),
        Reaped::default(),
        "just before the lease runs out"
    );
    assert!(
        repos[0]
            .heartbeat(&[first], lease, clock.now())
            .unwrap()
            .is_empty()
    );
    clock.wait_until(t0 + l + margin);
    assert_eq!(
        repos[1].reap(2, &lost, clock.now()).unwrap(),
        Reaped::default(),
        "extended"
    );
    clock.wait_until(t0 + 2 * l - 2 * margin);
    assert_eq!(
        repos[1].reap(2, &lost, clock.now()).unwrap(),
        Reaped::default(),
        "just before the extended lease runs out"
    );
    clock.wait_until(t0 + 2 * l + margin);
    let reaped = repos[1].reap(2, &lost, clock.now()).unwrap();
    assert_eq!(reaped.requeued, [id]);
    assert!(reaped.failed.is_empty());
    let second = repos[2]
        .claim("takes over", lease, clock.now())
        .unwrap()
        .unwrap();
    assert_eq!(second.id, id);
    assert!(second.token > first.token);
    // The first worker wakes up late: refused, whatever it writes.
    let now = clock.now();
    assert!(!repos[0].progress(first, "solve", 0.5, now).unwrap());
    assert_eq!(
        repos[0].heartbeat(&[first, second], lease, now).unwrap(),
        [first]
    );
    assert!(!repos[0].finish(first, &succeeded(1), now).unwrap());
    assert!(!repos[0].requeue(first).unwrap());
    assert_eq!(
        repos[3].get(id).unwrap().unwrap().status,
        JobStatus::Running
    );
    assert!(repos[2].finish(second, &succeeded(2), now).unwrap());
    assert!(
        !repos[2].finish(second, &succeeded(3), now).unwrap(),
        "once"
    );
    let rec = repos[3].get(id).unwrap().unwrap();
    assert_eq!(rec.status, JobStatus::Succeeded);
    assert_eq!(rec.attempts, 2);
    assert_eq!(rec.result, Some(serde_json::json!({"width": 2})));

    drop(repos);
    let again = backend.open(db);
    assert_eq!(again.get(id).unwrap().unwrap().attempts, 2);
}

/// The second attempt's lease runs out too: with two attempts allowed that was the last,
/// and the job fails with the reaper's problem; its worker's finish is refused.
fn last_attempt_fails<B: Backend>(backend: &B, db: &B::Db) {
    let clock = backend.clock();
    let (lease, margin) = (clock.lease(), clock.margin());
    let l = lease.as_millis() as i64;
    let repo = backend.open(db);
    let id = queue(&*repo, "t", 1);
    let t = clock.now();
    repo.claim("dies", lease, t).unwrap().unwrap();
    clock.wait_until(t + l + margin);
    assert_eq!(repo.reap(2, &lost, clock.now()).unwrap().requeued, [id]);
    let t = clock.now();
    let second = repo.claim("dies too", lease, t).unwrap().unwrap();
    assert_eq!(second.id, id);
    clock.wait_until(t + l + margin);
    let reaped = repo.reap(2, &lost, clock.now()).unwrap();
    assert_eq!(reaped.failed, [id]);
    assert!(reaped.requeued.is_empty());
    let rec = repo.get(id).unwrap().unwrap();
    assert_eq!((rec.status, rec.attempts), (JobStatus::Failed, 2));
    let detail = rec.error.unwrap().detail;
    assert_eq!(detail, lost(id).detail);
    assert!(detail.contains("stopped answering"));
    assert!(!repo.finish(second, &succeeded(1), clock.now()).unwrap());
}

/// With one attempt allowed, the first lease that runs out fails the job.
fn first_attempt_fails_at_one<B: Backend>(backend: &B, db: &B::Db) {
    let clock = backend.clock();
    let (lease, margin) = (clock.lease(), clock.margin());
    let repos = backend.open_many(db, 2);
    let doomed = job("b", 60);
    assert!(accepted(&*repos[0], &doomed, 100));
    let t = clock.now();
    repos[0].claim("dies", lease, t).unwrap().unwrap();
    clock.wait_until(t + lease.as_millis() as i64 + margin);
    assert_eq!(
        repos[1].reap(1, &lost, clock.now()).unwrap().failed,
        [doomed.id]
    );
    let rec = repos[1].get(doomed.id).unwrap().unwrap();
    assert_eq!(rec.status, JobStatus::Failed);
    assert!(rec.error.unwrap().detail.contains("stopped answering"));
}
