// ============================================================================
//  flarelab daemon: Journal, JournalLoad
// ============================================================================
//
// The daemon's job records on disk, so that a daemon that crashed or was killed finds its jobs
// again. One file per job, `<state dir>/jobs/<job id>.json`: the message flarelab.v1.Job (its
// configuration included) in the protobuf JSON mapping. Each save writes a temporary file, flushes
// it to disk, renames it over the old record and flushes the directory, so a record is always
// whole: the old one or the new one; a save that returns an error (a full or read-only disk, a
// failed flush) may not have reached the disk, and the daemon does not act on it. A record that
// cannot be read (torn by a broken disk, edited by hand, larger than kJournalMaxRecordBytes, not a
// regular file) is not fatal: it is renamed to `<name>.corrupt`, kept for a person to look at, and
// reported. Every record the journal writes reads back: save refuses one over the limit, and the
// daemon refuses a job whose record could grow past it (JobManager::start).
//
// The record says what the job was asked and how far it had got; what is on disk is the sweep's
// own business (hdr/sweep.h): a resumed job trusts the sweep's manifest, not the record, for
// which frames are safely written.
#pragma once

#include <string>
#include <vector>

#include "common/result.h"
#include "proto/daemon.pb.h"

namespace flarelab::daemon {

struct JournalLoad {
    std::vector<flarelab::v1::Job> jobs;  // by id
    std::vector<std::string> warnings;    // records set aside, one line each naming the file
};

// The largest record read back. A record holds the job's lens file, at most 1 MiB by default
// (SweepLimits::max_prescription_bytes), which protobuf's JSON writer may grow sixfold: '<', '>'
// and control characters become \u003c, \u003e, \u0001.
inline constexpr int64_t kJournalMaxRecordBytes = int64_t{16} << 20;

class Journal {
public:
    // Creates `<state_dir>/jobs` if needed. IoError when it cannot.
    static Result<Journal> open(const std::string& state_dir);

    // Writes the job's record (atomically, see above). IoError naming the file; InvalidArgument
    // when the record would exceed kJournalMaxRecordBytes (nothing is written).
    Status save(const flarelab::v1::Job& job) const;
    // The size of the job's record as save writes it; Internal when it cannot be printed.
    static Result<int64_t> recordBytes(const flarelab::v1::Job& job);
    // Every record in the journal.
    Result<JournalLoad> load() const;
    // Deletes the record of job `id` (a job forgotten); OK when there is none. IoError naming
    // the file.
    Status remove(const std::string& id) const;
    // Parses one record; ParseError naming `name` and what is wrong (also for the fuzzer).
    static Result<flarelab::v1::Job> parse(const std::string& json, const std::string& name);

    const std::string& directory() const { return directory_; }

private:
    explicit Journal(std::string directory) : directory_(std::move(directory)) {}
    std::string directory_;
};

// "job-000042" for 42; the number of such an id, or 0 when it is not one.
std::string jobId(uint64_t number);
uint64_t jobNumber(const std::string& id);

}  // namespace flarelab::daemon
