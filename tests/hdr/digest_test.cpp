#include "hdr/digest.h"

#include <gtest/gtest.h>

#include <filesystem>
#include <fstream>
#include <string>

namespace flarelab::hdr {
namespace {

namespace fs = std::filesystem;

// FIPS 180-2's examples, and the empty message.
TEST(Digest, Sha256OfKnownMessages) {
    EXPECT_EQ(*sha256Hex("abc"),
              "ba7816bf8f01cfea414140de5dae2223b00361a396177a9cb410ff61f20015ad");
    EXPECT_EQ(*sha256Hex(""), "e3b0c44298fc1c149afbf4c8996fb92427ae41e4649b934ca495991b7852b855");
    EXPECT_EQ(*sha256Hex("abcdbcdecdefdefgefghfghighijhijkijkljklmklmnlmnomnopnopq"),
              "248d6a61d20638b8e5c026930c3e6039a33ce45964ff2167f6ecedd419db06c1");
}

// A file is hashed in chunks: one larger than a chunk gives the digest of its bytes in one piece;
// a missing file is an error that names it; a hash is finished once.
TEST(Digest, FilesInChunksAndErrors) {
    const fs::path file = fs::temp_directory_path() / "flarelab_digest_test.bin";
    std::string bytes;
    for (int i = 0; i < 200000; ++i) bytes.push_back(static_cast<char>((i * 131) % 251));
    {
        std::ofstream out(file, std::ios::binary);
        out << bytes;
    }
    auto from_file = sha256File(file.string());
    ASSERT_TRUE(from_file) << from_file.error().message;
    EXPECT_EQ(*from_file, *sha256Hex(bytes));
    EXPECT_EQ(from_file->size(), 64u);
    fs::remove(file);
    auto missing = sha256File(file.string());
    ASSERT_FALSE(missing);
    EXPECT_NE(missing.error().message.find(file.string()), std::string::npos);

    Sha256 hash;
    ASSERT_TRUE(hash.update("ab"));
    ASSERT_TRUE(hash.update("c"));
    EXPECT_EQ(*hash.finishHex(), *sha256Hex("abc"));
    EXPECT_FALSE(hash.finishHex());
    EXPECT_FALSE(hash.update("d"));
}

}  // namespace
}  // namespace flarelab::hdr
