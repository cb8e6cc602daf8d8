//! Process supervisor: to come.
