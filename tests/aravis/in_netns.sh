#!/bin/sh
# Runs a test binary in a network namespace of its own (`unshare -n`: only a loopback
# interface, down until the test brings it up), so that the GigE Vision discovery broadcasts of
# Aravis and the fake camera's port 3956 stay off the real network and apart from other tests
# running at the same time. Listing the tests (--gtest_list_tests, at build time) needs no
# namespace. Where namespaces are not permitted the test fails saying so; it never passes
# without having run.
for arg in "$@"; do
    case "$arg" in
        --gtest_list_tests) exec "$@" ;;
    esac
done
if ! unshare -n true 2>/dev/null; then
    echo "in_netns.sh: cannot create a network namespace (unshare -n failed: it needs root or" \
         "CAP_SYS_ADMIN, as in CI); the GigE Vision tests against Aravis's fake camera need one" \
         "so that their discovery broadcasts stay off the real network. Run ctest as root, or" \
         "leave these tests out with ctest -LE aravis." >&2
    exit 1
fi
exec unshare -n "$@"
