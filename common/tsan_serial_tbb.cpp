// Linked into every executable of the tsan preset only (CMakeLists.txt, FLARELAB_TSAN).
//
// Debian's oneTBB is not built with ThreadSanitizer, so the synchronization inside it (a
// parallel_for's workers joining the caller) is invisible to it: every loop body that writes a
// buffer the caller reads afterwards is reported as a race, and the workers' stacks cannot be
// restored for a suppression to match. Here TBB runs every parallel algorithm on the calling
// thread, so what ThreadSanitizer reports is between flarelab's own threads (the daemon's
// manager, journal, capture, processing and fit threads, the cameras' and heads' threads),
// which is what it can judge. The loops' own parallelism is left to the tests that compare the
// parallel renderer and merge with serial references bit for bit.
#include <tbb/global_control.h>

namespace {
const tbb::global_control kSerialTbb(tbb::global_control::max_allowed_parallelism, 1);
}  // namespace
