//! guardian-client: the thin library a motion planner links to ask `guardiand` whether a
//! candidate trajectory is the task it claims to be. It speaks iceoryx2 shared memory and
//! pulls in no model code.
#![forbid(unsafe_code)]
#![warn(missing_docs)]
