//! What the audit of a carried cut finds wrong ([`AuditError`], `audit.rs`), and what a
//! walk of a frontier's bucket lists finds wrong ([`ListError`], `buckets.rs`): for tests,
//! each naming the diamond, the frontier, the list or bucket, and what was expected. A
//! diamond is named by its centre `(x, z)`; a frontier by `split` or `merge`.

/// A carried cut that is not what its split set says it must be ([`super::Coherent::audit`]).
#[derive(Clone, Debug, PartialEq, thiserror::Error)]
pub enum AuditError {
    #[error("split {split:?} has the unsplit parent {parent:?}")]
    UnsplitParent {
        split: (u32, u32),
        parent: (u32, u32),
    },
    /// The cut's kept counts differ from those recounted from its split set.
    #[error(
        "{triangles} triangles and {splits} splits counted, {cut_triangles} and {cut_splits} \
         in the cut"
    )]
    Counts {
        triangles: u32,
        splits: u32,
        cut_triangles: u32,
        cut_splits: usize,
    },
    #[error("{frontier} candidates listed twice")]
    ListedTwice { frontier: &'static str },
    #[error("{frontier} candidates: {missing} missing, {extra} that should not be there")]
    Candidates {
        frontier: &'static str,
        missing: usize,
        extra: usize,
    },
    /// A merge candidate that nothing forces is not worth splitting at this camera.
    #[error(
        "{at:?} is split, forced by nothing, but not worth splitting here (priority {prio} px)"
    )]
    Unforced { at: (u32, u32), prio: f32 },
    #[error("{frontier} candidates: free places listed wrong")]
    FreeListedWrong { frontier: &'static str },
    /// The frontier's lists are ill formed.
    #[error("{frontier} candidates: {error}")]
    Lists {
        frontier: &'static str,
        error: ListError,
    },
    #[error(
        "{frontier} candidate {at:?} queued in bucket {bucket}, {by_evaluation:?} by its evaluation"
    )]
    Bucket {
        frontier: &'static str,
        at: (u32, u32),
        bucket: usize,
        by_evaluation: Option<usize>,
    },
    #[error("{frontier} candidates: free place {place} queued or scheduled")]
    FreeQueued {
        frontier: &'static str,
        place: usize,
    },
    #[error("{frontier} candidate {at:?} not indexed")]
    NotIndexed {
        frontier: &'static str,
        at: (u32, u32),
    },
    #[error("{frontier} candidate {at:?} queued {times} times, {want} by its evaluation")]
    Queued {
        frontier: &'static str,
        at: (u32, u32),
        times: usize,
        want: usize,
    },
    #[error("{frontier} candidates: free place {place} scheduled")]
    FreeScheduled {
        frontier: &'static str,
        place: usize,
    },
    /// Scheduled on an odometer (`travel`, `turn`) other than once when it has error (or
    /// at all when it is exact).
    #[error(
        "{frontier} candidate {at:?} scheduled {times} times by its {odometer}, {want} by its \
         error"
    )]
    Scheduled {
        frontier: &'static str,
        at: (u32, u32),
        times: usize,
        odometer: &'static str,
        want: usize,
    },
    /// Due on an odometer before its key now: what was due was not taken.
    #[error("{frontier} candidate {at:?} was due by its {odometer} at {key}, {now} now")]
    Overdue {
        frontier: &'static str,
        at: (u32, u32),
        odometer: &'static str,
        key: u32,
        now: u32,
    },
}

/// A frontier's queue or schedule whose lists are ill formed (for the audit).
#[derive(Clone, Debug, PartialEq, thiserror::Error)]
pub enum ListError {
    #[error("list {list} names member {member}, past the members")]
    PastMembers { list: usize, member: u32 },
    /// A member's previous is not the member before it in the walk.
    #[error("list {list}: member {member}'s previous is {prev}, not {want}")]
    Previous {
        list: usize,
        member: u32,
        prev: u32,
        want: u32,
    },
    #[error("list {list} does not come back to its head")]
    Endless { list: usize },
    /// A queue bucket marked non-empty (`marked`) when its list is empty, or the reverse.
    #[error("queue bucket {bucket} marked {marked}, {len} long")]
    QueueMarked {
        bucket: usize,
        marked: bool,
        len: usize,
    },
    /// A queue bucket's highest priority is not the one it keeps.
    #[error("queue bucket {bucket}'s highest is {most}, kept as {known}")]
    Highest {
        bucket: usize,
        most: f32,
        known: f32,
    },
    #[error("schedule bucket {bucket} marked wrong")]
    ScheduleMarked { bucket: usize },
    #[error("schedule bucket {bucket} names member {member}, past the members")]
    SchedulePast { bucket: usize, member: u32 },
    /// A scheduled member's link (`prev`, `next`) does not name its place `at` in the
    /// bucket, or its entry names another bucket.
    #[error(
        "member {member} at {at} of schedule bucket {bucket} has link Link {{ prev: {prev}, \
         next: {next} }}, bucket {entry}"
    )]
    ScheduleLink {
        member: u32,
        at: usize,
        bucket: usize,
        prev: u32,
        next: u32,
        entry: usize,
    },
    /// A key below its bucket's bound (`last`: the last key taken).
    #[error("key {key} in schedule bucket {bucket} (bound {bound}, last {last})")]
    ScheduleKey {
        key: u32,
        bucket: usize,
        bound: u32,
        last: u32,
    },
    #[error("{listed} scheduled, {counted} counted")]
    ScheduleCount { listed: usize, counted: usize },
}
