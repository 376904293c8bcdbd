// Runs a libFuzzer target's entry point over files, without libFuzzer: the normal build links this
// with each fuzzer so ctest replays the corpus, the shipped lenses and the broken test files on
// every compiler, sanitizers or not. Arguments are files or directories (searched recursively);
// a path that does not exist, or a run over no file at all, fails.
#include <unistd.h>

#include <algorithm>
#include <csignal>
#include <cstddef>
#include <cstdint>
#include <filesystem>
#include <fstream>
#include <iostream>
#include <iterator>
#include <string>
#include <string_view>
#include <system_error>
#include <vector>

extern "C" int LLVMFuzzerTestOneInput(const uint8_t* data, size_t size);

namespace {

namespace fs = std::filesystem;

// The input being run, for the crash handler: a trap or sanitizer abort would otherwise leave
// ctest's log without the file that caused it.
const char* current_input = nullptr;

extern "C" void reportCrashingInput(int signal_number) {
    if (current_input != nullptr) {
        constexpr std::string_view kWhat = "replay: crashed on input ";
        [[maybe_unused]] ssize_t n = write(STDERR_FILENO, kWhat.data(), kWhat.size());
        const std::string_view path(current_input);
        n = write(STDERR_FILENO, path.data(), path.size());
        n = write(STDERR_FILENO, "\n", 1);
    }
    std::signal(signal_number, SIG_DFL);
    std::raise(signal_number);
}

bool readFile(const fs::path& path, std::vector<uint8_t>& bytes) {
    std::ifstream in(path, std::ios::binary);
    if (!in) return false;
    bytes.assign(std::istreambuf_iterator<char>(in), std::istreambuf_iterator<char>());
    return !in.bad();
}

}  // namespace

int main(int argc, char** argv) {
    if (argc < 2) {
        std::cerr << "usage: " << argv[0] << " FILE_OR_DIR...\n";
        return 2;
    }
    std::vector<fs::path> files;
    for (int i = 1; i < argc; ++i) {
        const fs::path root(argv[i]);
        std::error_code ec;
        if (fs::is_regular_file(root, ec)) {
            files.push_back(root);
        } else if (fs::is_directory(root, ec)) {
            for (const auto& entry : fs::recursive_directory_iterator(root, ec))
                if (entry.is_regular_file()) files.push_back(entry.path());
            if (ec) {
                std::cerr << root.string() << ": " << ec.message() << "\n";
                return 1;
            }
        } else {
            std::cerr << root.string() << ": no such file or directory\n";
            return 1;
        }
    }
    // Sorted, so a failure names the same input first on every machine.
    std::sort(files.begin(), files.end());
    for (const int signal_number : {SIGILL, SIGABRT, SIGSEGV, SIGFPE, SIGBUS})
        std::signal(signal_number, reportCrashingInput);
    std::vector<uint8_t> bytes;
    std::string current;
    for (const fs::path& file : files) {
        current = file.string();
        current_input = current.c_str();
        if (!readFile(file, bytes)) {
            std::cerr << file.string() << ": cannot read\n";
            return 1;
        }
        LLVMFuzzerTestOneInput(bytes.data(), bytes.size());
    }
    std::cout << "replayed " << files.size() << " inputs\n";
    return files.empty() ? 1 : 0;
}
