// Only who should gets in: the state directory, the lock, the token and TLS files are checked;
// TCP needs the token and, beyond loopback, TLS; loopback is resolved, not read as text; rate
// limits and control follow the peer the kernel or the network vouches for, not a name the
// client picks; ended jobs are forgotten by age and count, their sweeps kept.
#include "daemon/access.h"

#include <gtest/gtest.h>
#include <pwd.h>
#include <sys/stat.h>

#include <chrono>
#include <thread>

#include "apps/daemon_commands.h"
#include "daemon/journal.h"
#include "tests/apps/command_runner.h"
#include "tests/daemon/daemon_process.h"

namespace flarelab::daemon {
namespace {

using namespace testing;

void writeFile(const std::string& path, const std::string& text, fs::perms mode) {
    std::ofstream(path) << text;
    fs::permissions(path, mode, fs::perm_options::replace);
}

constexpr fs::perms kOwnerOnly = fs::perms::owner_read | fs::perms::owner_write;
constexpr fs::perms kWorldReadable = kOwnerOnly | fs::perms::group_read | fs::perms::others_read;
constexpr char kToken[] = "0123456789abcdef-token";

TEST(Access, LoopbackIsResolvedNotReadAsText) {
    EXPECT_TRUE(checkLoopbackAddress("127.0.0.1:5000"));
    EXPECT_TRUE(checkLoopbackAddress("127.3.2.1:5000"));
    EXPECT_TRUE(checkLoopbackAddress("[::1]:5000"));
    EXPECT_TRUE(checkLoopbackAddress("[::ffff:127.0.0.1]:5000"));
    EXPECT_TRUE(checkLoopbackAddress("localhost:5000"));
    for (const char* outside :
         {"0.0.0.0:5000", "[::]:5000", ":5000", "10.1.2.3:5000", "127.0.0.1.example.invalid:5000",
          "127.evil.invalid:5000", "[::ffff:10.0.0.1]:5000", "127.0.0.1"}) {
        const auto checked = checkLoopbackAddress(outside);
        EXPECT_FALSE(checked) << outside;
        if (!checked) {
            EXPECT_EQ(checked.error().code, ErrorCode::InvalidArgument);
        }
    }
    const auto named = checkLoopbackAddress("10.1.2.3:1");
    ASSERT_FALSE(named);
    EXPECT_NE(named.error().message.find("10.1.2.3"), std::string::npos);
}

TEST(Access, AStateDirectoryOthersCanWriteOrAnotherUserOwnsIsRefused) {
    TempDir dir;
    const std::string state = privateStateDir(dir.path);
    EXPECT_TRUE(checkPrivateDirectory(state, "--state-dir"));
    fs::permissions(state, fs::perms::owner_all | fs::perms::group_read | fs::perms::group_exec,
                    fs::perm_options::replace);
    EXPECT_TRUE(checkPrivateDirectory(state, "--state-dir"));  // 0750: the group reaches in
    for (const fs::perms writable : {fs::perms::group_write, fs::perms::others_write}) {
        fs::permissions(state, fs::perms::owner_all | writable, fs::perm_options::replace);
        const auto refused = checkPrivateDirectory(state, "--state-dir");
        ASSERT_FALSE(refused);
        EXPECT_NE(refused.error().message.find("chmod go-w " + state), std::string::npos)
            << refused.error().message;
    }
    fs::permissions(state, fs::perms::owner_all, fs::perm_options::replace);
    if (::geteuid() == 0) {  // only root can give a directory away
        const passwd* nobody = ::getpwnam("nobody");
        ASSERT_NE(nobody, nullptr);
        ASSERT_EQ(::chown(state.c_str(), nobody->pw_uid, nobody->pw_gid), 0);
        const auto refused = checkPrivateDirectory(state, "--state-dir");
        ASSERT_FALSE(refused);
        EXPECT_NE(refused.error().message.find("owned by uid " + std::to_string(nobody->pw_uid)),
                  std::string::npos)
            << refused.error().message;
    }
    EXPECT_FALSE(checkPrivateDirectory(dir.path + "/absent", "--state-dir"));
}

TEST(Access, ASecretOthersCanReadIsRefusedAndAFifoIsNotWaitedOn) {
    TempDir dir;
    const std::string token = dir.path + "/token";
    writeFile(token, std::string(kToken) + "\n", kWorldReadable);
    const auto refused = readSecretFile(token, "--token-file");
    ASSERT_FALSE(refused);
    EXPECT_NE(refused.error().message.find("chmod 600 " + token), std::string::npos)
        << refused.error().message;
    fs::permissions(token, kOwnerOnly, fs::perm_options::replace);
    auto read = readSecretFile(token, "--token-file");
    ASSERT_TRUE(read) << read.error().message;
    EXPECT_EQ(*read, std::string(kToken) + "\n");
    const std::string fifo = dir.path + "/fifo";
    ASSERT_EQ(::mkfifo(fifo.c_str(), 0600), 0);
    const auto not_file = readSecretFile(fifo, "--token-file");
    ASSERT_FALSE(not_file);
    EXPECT_NE(not_file.error().message.find("not a regular file"), std::string::npos);
}

TEST(Access, TcpNeedsATokenAndBeyondLoopbackTls) {
    TempDir dir;
    fs::create_directories(dir.path + "/output");
    ManagerOptions manager;
    manager.runner.state_dir = dir.path;
    manager.runner.output_root = fs::canonical(dir.path + "/output").string();
    auto made = JobManager::open(manager);
    ASSERT_TRUE(made);
    ServerOptions options;
    options.tcp_address = "127.0.0.1:0";
    auto no_token = DaemonServer::start(**made, options);
    ASSERT_FALSE(no_token);
    EXPECT_NE(no_token.error().message.find("needs a token"), std::string::npos);
    options.service.token = kToken;
    options.tcp_address = "0.0.0.0:0";
    auto wide = DaemonServer::start(**made, options);
    ASSERT_FALSE(wide);
    EXPECT_NE(wide.error().message.find("--allow-remote"), std::string::npos);
    options.allow_remote = true;
    auto clear = DaemonServer::start(**made, options);
    ASSERT_FALSE(clear);
    EXPECT_NE(clear.error().message.find("needs TLS"), std::string::npos);
}

// A self-signed certificate for localhost and 127.0.0.1 made by openssl(1); false when openssl
// is not there.
bool makeCertificate(const std::string& cert, const std::string& key) {
    const std::string command =
        "openssl req -x509 -newkey rsa:2048 -nodes -days 2 -subj /CN=localhost "
        "-addext subjectAltName=DNS:localhost,IP:127.0.0.1 -keyout " +
        key + " -out " + cert + " >/dev/null 2>&1";
    if (std::system(command.c_str()) != 0) return false;
    fs::permissions(key, kOwnerOnly, fs::perm_options::replace);
    return true;
}

TEST(Access, RemoteListeningTakesTlsAndTheClientTrustsTheCaItIsGiven) {
    TempDir dir;
    const std::string cert = dir.path + "/cert.pem", key = dir.path + "/key.pem";
    if (!makeCertificate(cert, key)) GTEST_SKIP() << "openssl(1) cannot make a certificate here";
    ServerOptions server;
    server.tcp_address = "127.0.0.1:0";  // beyond loopback in a lab; loopback in the test
    server.allow_remote = true;
    server.tls_cert_file = cert;
    server.tls_key_file = key;
    server.service.token = kToken;
    testToken() = kToken;
    Daemon daemon(dir.path + "/state", {}, server);
    const std::string target = "localhost:" + std::to_string(daemon.server().tcpPort());
    grpc::SslCredentialsOptions trust;
    trust.pem_root_certs = readText(cert);
    auto secure = v1::FlareLab::NewStub(grpc::CreateChannel(target, grpc::SslCredentials(trust)));
    v1::RigDescription rig;
    auto ctx = context("tls", 10.0);
    const grpc::Status ok = secure->DescribeRig(ctx.get(), {}, &rig);
    EXPECT_TRUE(ok.ok()) << ok.error_message();
    // In clear, nothing gets through.
    auto plain = daemon.stub(target);
    auto clear = context("plain", 5.0);
    EXPECT_FALSE(plain->DescribeRig(clear.get(), {}, &rig).ok());
    testToken().clear();
    // The command line with --tls-ca.
    const std::string token_file = dir.path + "/token";
    writeFile(token_file, kToken, kOwnerOnly);
    const auto run = apps::testing::runCommand(
        [](CLI::App& app, std::ostream& out, std::ostream& err, int& code) {
            apps::addRigCommands(app, out, err, code);
        },
        {"rig", "status", "--address", target, "--tls-ca", cert, "--token-file", token_file});
    EXPECT_EQ(run.code, 0) << run.err;
    EXPECT_NE(run.out.find("output root"), std::string::npos) << run.out;
    // A key others can read is refused.
    fs::permissions(key, kWorldReadable, fs::perm_options::replace);
    ServerOptions loose = server;
    loose.socket_path.clear();
    ManagerOptions manager;
    manager.runner.state_dir = dir.path + "/state";
    manager.runner.output_root = daemon.output_root;
    daemon.stop();
    auto made = JobManager::open(manager);
    ASSERT_TRUE(made);
    auto refused = DaemonServer::start(**made, loose);
    ASSERT_FALSE(refused);
    EXPECT_NE(refused.error().message.find("chmod 600"), std::string::npos);
}

TEST(Access, ControlNeedsTheSameNameFromTheSamePeer) {
    TempDir dir;
    ServerOptions server;
    server.tcp_address = "127.0.0.1:0";
    server.service.token = kToken;
    testToken() = kToken;
    Daemon daemon(dir.path, {}, server);
    auto unix_stub = daemon.stub();
    auto tcp_stub = daemon.stub("127.0.0.1:" + std::to_string(daemon.server().tcpPort()));
    v1::Job job;
    ASSERT_TRUE(
        startSweep(*unix_stub, simConfig("owned", 0.0, 4.0, 0.2, false), &job, "alice").ok());
    EXPECT_EQ(job.controller(), "alice");
    EXPECT_EQ(job.controller_peer(), "uid " + std::to_string(::geteuid()));
    // "alice" over TCP is another peer: a name is not an identity.
    v1::JobControlRequest request;
    request.set_job_id(job.id());
    v1::Job answer;
    auto impostor = context("alice");
    const grpc::Status denied = tcp_stub->PauseJob(impostor.get(), request, &answer);
    EXPECT_EQ(denied.error_code(), grpc::StatusCode::PERMISSION_DENIED) << denied.error_message();
    auto owner = context("alice");
    EXPECT_TRUE(unix_stub->PauseJob(owner.get(), request, &answer).ok());
    request.set_take_control(true);
    auto taker = context("alice");
    EXPECT_TRUE(tcp_stub->CancelJob(taker.get(), request, &answer).ok());
    EXPECT_EQ(answer.controller_peer(), "ipv4:127.0.0.1");
    EXPECT_EQ(waitFor(*unix_stub, job.id(), ended).state(), v1::CANCELLED);
    testToken().clear();
}

TEST(Access, TheSocketIsBoundPrivatelyAndTheUmaskIsLeftAloneForTheOtherThreads) {
    TempDir dir;
    // Another thread makes directories all along the server's start: the umask is the
    // process's, so a daemon that changes it to set its socket's mode changes theirs too.
    const mode_t before = ::umask(0022);
    std::atomic<bool> starting{true};
    std::atomic<int> made{0}, wrong{0};
    std::thread other([&] {
        const std::string probe = dir.path + "/probe";
        while (starting) {
            if (::mkdir(probe.c_str(), 0777) != 0) continue;
            struct stat s {};
            if (::stat(probe.c_str(), &s) == 0 && (s.st_mode & 0777) != 0755) ++wrong;
            ++made;
            ::rmdir(probe.c_str());
        }
    });
    // Several starts: the window of a umask changed around the socket's creation is short.
    for (int i = 0; i < 9; ++i) Daemon(dir.path + "/state-" + std::to_string(i)).stop();
    auto daemon = std::make_unique<Daemon>(dir.path + "/state");
    starting = false;
    other.join();
    EXPECT_EQ(::umask(before), 0022u);
    EXPECT_GT(made.load(), 0);
    EXPECT_EQ(wrong.load(), 0) << "directories made during the start had another mode";
    struct stat s {};
    ASSERT_EQ(::stat(daemon->socket.c_str(), &s), 0);
    EXPECT_TRUE(S_ISSOCK(s.st_mode));
    EXPECT_EQ(s.st_mode & 0777, 0660u);
    for (const auto& entry : fs::directory_iterator(dir.path + "/state"))
        EXPECT_NE(entry.path().filename().string().rfind(".s-", 0), 0u)
            << "the private directory was left: " << entry.path();
    auto stub = daemon->stub();
    v1::RigDescription rig;
    auto ctx = context();
    EXPECT_TRUE(stub->DescribeRig(ctx.get(), {}, &rig).ok());
}

// ---- flarelabd's own checks ----

TEST(Flarelabd, RefusesAStateDirectoryOthersCanWrite) {
    TempDir dir;
    const std::string state = privateStateDir(dir.path);
    fs::permissions(state, fs::perms::all, fs::perm_options::replace);
    const std::string log = dir.path + "/log";
    FlarelabdProcess daemon({"--state-dir", state}, log);
    const auto status = daemon.waitExit(20.0);
    EXPECT_TRUE(exitedWith(status, 1)) << "it ran in a directory anyone can write\n"
                                       << readText(log);
    EXPECT_NE(readText(log).find("chmod go-w"), std::string::npos) << readText(log);
    // One it makes itself is private.
    const std::string fresh = dir.path + "/fresh/state";
    FlarelabdProcess made({"--state-dir", fresh}, log);
    ASSERT_TRUE(connectWhenUp(fresh + "/flarelabd.sock")) << readText(log);
    EXPECT_EQ(fs::status(fresh).permissions() & fs::perms::all,
              fs::perms::owner_all | fs::perms::group_read | fs::perms::group_exec);
}

TEST(Flarelabd, RefusesALockFileThatIsALinkAndLeavesItsTargetAlone) {
    TempDir dir;
    const std::string state = privateStateDir(dir.path);
    const std::string target = dir.path + "/precious";
    std::ofstream(target) << "someone's data";
    fs::create_symlink(target, state + "/flarelabd.lock");
    const std::string log = dir.path + "/log";
    FlarelabdProcess daemon({"--state-dir", state}, log);
    const auto status = daemon.waitExit(20.0);
    EXPECT_TRUE(exitedWith(status, 1)) << readText(log);
    EXPECT_NE(readText(log).find("symbolic link"), std::string::npos) << readText(log);
    EXPECT_EQ(readText(target), "someone's data");
}

TEST(Flarelabd, RefusesATokenOthersCanReadTcpWithoutATokenAndRemoteWithoutTls) {
    TempDir dir;
    const std::string state = privateStateDir(dir.path), log = dir.path + "/log";
    const std::string token = dir.path + "/token";
    writeFile(token, kToken, kWorldReadable);
    {
        FlarelabdProcess daemon({"--state-dir", state, "--token-file", token}, log);
        EXPECT_TRUE(exitedWith(daemon.waitExit(20.0), 1)) << readText(log);
        EXPECT_NE(readText(log).find("chmod 600 " + token), std::string::npos) << readText(log);
    }
    fs::permissions(token, kOwnerOnly, fs::perm_options::replace);
    const std::vector<std::pair<std::vector<std::string>, std::string>> refused = {
        {{"--listen", "127.0.0.1:0"}, "needs --token-file"},
        {{"--listen", "0.0.0.0:0", "--allow-remote", "--token-file", token}, "needs TLS"},
        {{"--listen", "127.0.0.1.evil.invalid:0", "--token-file", token}, "not loopback"},
        {{"--listen", "[::]:0", "--token-file", token}, "--allow-remote"},
    };
    for (size_t i = 0; i < refused.size(); ++i) {
        const auto& [flags, why] = refused[i];
        std::vector<std::string> args = {"--state-dir", state};
        args.insert(args.end(), flags.begin(), flags.end());
        const std::string own_log = dir.path + "/log-" + std::to_string(i);
        FlarelabdProcess daemon(args, own_log);
        const auto status = daemon.waitExit(20.0);
        EXPECT_TRUE(exitedWith(status, 2)) << flags[1] << ": " << readText(own_log);
        EXPECT_NE(readText(own_log).find(why), std::string::npos)
            << flags[1] << ": " << readText(own_log);
    }
}

// ---- forgetting ended jobs ----

v1::Job endedRecord(uint64_t number, const std::string& output_dir, double ended_unix_s) {
    v1::Job job;
    job.set_id(jobId(number));
    job.set_state(v1::SUCCEEDED);
    job.set_phase(v1::FINISHED);
    job.set_output_dir(output_dir);
    job.set_request_id("request-" + std::to_string(number));
    job.set_updated_unix_s(ended_unix_s);
    return job;
}

TEST(Prune, EndedJobsBeyondTheCountOrTheAgeAreForgottenAndTheirSweepsKept) {
    TempDir dir;
    const double now =
        std::chrono::duration<double>(std::chrono::system_clock::now().time_since_epoch()).count();
    {
        auto journal = Journal::open(dir.path);
        ASSERT_TRUE(journal);
        // Two of 40 days ago, one of yesterday.
        ASSERT_TRUE(journal->save(endedRecord(1, dir.path + "/output/a", now - 40 * 86400.0)));
        ASSERT_TRUE(journal->save(endedRecord(2, dir.path + "/output/b", now - 40 * 86400.0)));
        ASSERT_TRUE(journal->save(endedRecord(3, dir.path + "/output/c", now - 86400.0)));
    }
    ManagerOptions options;
    options.keep_ended = 2;
    options.keep_ended_s = 30 * 86400.0;
    Daemon daemon(dir.path, options);
    auto stub = daemon.stub();
    std::vector<std::string> ids;
    for (const auto& j : daemon.manager().list()) ids.push_back(j.id());
    EXPECT_EQ(ids, std::vector<std::string>{"job-000003"});
    // The manager forgets a job at once and its recorder thread deletes the record after (a
    // record left by a crash in between is read back and forgotten again): within seconds.
    const auto deadline = std::chrono::steady_clock::now() + std::chrono::seconds(10);
    while ((fs::exists(dir.path + "/jobs/job-000001.json") ||
            fs::exists(dir.path + "/jobs/job-000002.json")) &&
           std::chrono::steady_clock::now() < deadline)
        std::this_thread::sleep_for(std::chrono::milliseconds(5));
    EXPECT_FALSE(fs::exists(dir.path + "/jobs/job-000001.json"));
    EXPECT_FALSE(fs::exists(dir.path + "/jobs/job-000002.json"));
    EXPECT_TRUE(fs::exists(dir.path + "/jobs/job-000003.json"));
    // Three sweeps more: only the newest two ended jobs stay, their sweeps all on disk.
    std::vector<std::string> outputs;
    for (const char* name : {"d", "e", "f"}) {
        v1::Job job;
        ASSERT_TRUE(startSweep(*stub, simConfig(name, 0.0, 0.2, 0.2), &job).ok());
        EXPECT_EQ(waitFor(*stub, job.id(), ended).state(), v1::SUCCEEDED);
        outputs.push_back(job.output_dir());
    }
    ids.clear();
    for (const auto& j : daemon.manager().list()) ids.push_back(j.id());
    EXPECT_EQ(ids, (std::vector<std::string>{"job-000005", "job-000006"}));
    for (const std::string& output : outputs) EXPECT_TRUE(fs::exists(output + "/manifest.json"));
    daemon.stop();
    std::vector<std::string> records;
    for (const auto& entry : fs::directory_iterator(dir.path + "/jobs"))
        records.push_back(entry.path().filename().string());
    std::sort(records.begin(), records.end());
    EXPECT_EQ(records, (std::vector<std::string>{"job-000005.json", "job-000006.json"}));
}

}  // namespace
}  // namespace flarelab::daemon
