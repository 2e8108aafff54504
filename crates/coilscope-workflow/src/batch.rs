//! `coilscope identify REC1.wav REC2.wav …`: many records, each to its own result, a few at a
//! time, and one verdict over all of them.
//!
//! The batch is planned first (every result's file, before any work), then each record is
//! given to a worker the caller supplies (the command line starts itself once per record, so
//! that a record that crashes or runs away takes no other with it), and the exits are summed
//! up as the command's own would be: 0 every result trustworthy, 3 some written but not
//! trustworthy, 2 some failed.

use std::collections::{BTreeMap, VecDeque};
use std::path::{Path, PathBuf};
use std::sync::Mutex;

/// One record's job: the record and where its result goes (`OUT/NAME.json`).
#[derive(Clone, Debug, PartialEq, Eq, PartialOrd, Ord)]
pub struct Job {
    pub record: PathBuf,
    pub result: PathBuf,
}

/// The jobs of a batch into the directory `out`, `workers` at a time, checked before any
/// work: at least one worker, `out` a directory (not a `.json` file), and no two records that
/// would write the same result.
pub fn plan(records: &[PathBuf], out: &Path, workers: usize) -> Result<Vec<Job>, String> {
    if workers == 0 {
        return Err("--jobs 0: give at least 1".into());
    }
    if out.is_file() || out.extension().is_some_and(|e| e == "json") {
        return Err(format!(
            "{}: with {} recordings --out is a directory (each result is OUT/NAME.json)",
            out.display(),
            records.len()
        ));
    }
    let mut names = BTreeMap::new();
    let mut jobs = vec![];
    for r in records {
        let stem = r
            .file_stem()
            .map(|s| s.to_string_lossy().into_owned())
            .ok_or_else(|| format!("{}: not a file name", r.display()))?;
        if let Some(other) = names.insert(stem.clone(), r) {
            return Err(format!(
                "{} and {} would both write {stem}.json: give recordings with different names",
                other.display(),
                r.display()
            ));
        }
        jobs.push(Job { record: r.clone(), result: out.join(format!("{stem}.json")) });
    }
    Ok(jobs)
}

/// What a worker did with one record: its exit (0, 2 or 3, as the single command's), what it
/// said, and how long it took (s).
#[derive(Clone, Debug)]
pub struct Done {
    pub job: Job,
    pub exit: i32,
    pub text: String,
    pub seconds: f64,
}

/// Run the jobs, `workers` at a time, with `work` for each; `finished` sees each as it ends
/// (from the worker's thread, one at a time). The outcomes in the order of the records' paths.
pub fn run(
    jobs: Vec<Job>,
    workers: usize,
    work: impl Fn(&Job) -> (i32, String) + Sync,
    finished: impl Fn(&Done) + Sync,
) -> Vec<Done> {
    let workers = workers.max(1);
    let count = jobs.len();
    let queue = Mutex::new(jobs.into_iter().collect::<VecDeque<_>>());
    let done = Mutex::new(Vec::with_capacity(count));
    let report = Mutex::new(());
    std::thread::scope(|scope| {
        for _ in 0..workers.min(count) {
            scope.spawn(|| loop {
                let Some(job) = queue.lock().unwrap_or_else(|e| e.into_inner()).pop_front() else { break };
                let t = std::time::Instant::now();
                let (exit, text) = work(&job);
                let d = Done { job, exit, text, seconds: t.elapsed().as_secs_f64() };
                {
                    let _one_at_a_time = report.lock().unwrap_or_else(|e| e.into_inner());
                    finished(&d);
                }
                done.lock().unwrap_or_else(|e| e.into_inner()).push(d);
            });
        }
    });
    let mut done = done.into_inner().unwrap_or_else(|e| e.into_inner());
    done.sort_by(|a, b| a.job.cmp(&b.job));
    done
}

/// The batch's verdict: `Ok` when every result is trustworthy, else 2 when any record failed,
/// 3 when some were written but not trustworthy, with how many records were not.
pub fn verdict(done: &[Done]) -> Result<(), (i32, String)> {
    let bad = done.iter().filter(|d| d.exit != 0).count();
    // A record that failed outweighs one that was written but not trusted (an exit of 2 is
    // below 3, so not the largest exit).
    if done.iter().any(|d| d.exit != 0 && d.exit != 3) {
        Err((2, format!("{bad} of {} recordings failed or are not trustworthy", done.len())))
    } else if bad > 0 {
        Err((3, format!("{bad} of {} recordings gave results that are not trustworthy", done.len())))
    } else {
        Ok(())
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn two_records_that_would_write_one_result_are_refused_before_any_work() {
        let recs = [PathBuf::from("a/rec.wav"), PathBuf::from("b/rec.wav")];
        let e = plan(&recs, Path::new("out"), 2).unwrap_err();
        assert!(e.contains("a/rec.wav") && e.contains("b/rec.wav") && e.contains("rec.json"), "{e}");
        let e = plan(&recs[..1], Path::new("out.json"), 2).unwrap_err();
        assert!(e.contains("out.json") && e.contains("directory"), "{e}");
        assert!(plan(&recs[..1], Path::new("out"), 0).unwrap_err().contains("--jobs 0"));
    }

    #[test]
    fn every_job_runs_once_and_the_worst_exit_is_the_verdict() {
        let recs: Vec<PathBuf> = (0..7).map(|k| PathBuf::from(format!("r{k}.wav"))).collect();
        let jobs = plan(&recs, Path::new("out"), 3).expect("plan");
        let seen = Mutex::new(0);
        let done = run(
            jobs,
            3,
            |j| (if j.record.ends_with("r4.wav") { 3 } else { 0 }, String::new()),
            |_| *seen.lock().unwrap() += 1,
        );
        assert_eq!(*seen.lock().unwrap(), 7);
        assert_eq!(done.iter().map(|d| d.job.record.clone()).collect::<Vec<_>>(), recs);
        assert_eq!(done[2].job.result, Path::new("out").join("r2.json"));
        assert_eq!(verdict(&done).unwrap_err().0, 3);
        assert!(verdict(&done[..4]).is_ok());
        let mut failed = done.clone();
        failed[0].exit = 2;
        assert_eq!(verdict(&failed).unwrap_err(), (2, "2 of 7 recordings failed or are not trustworthy".to_string()));
    }
}
