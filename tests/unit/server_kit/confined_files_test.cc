// ConfinedDirectory: a requested path resolves inside its directory or is
// refused naming it; reads are of regular files, capped.

#include "behaviorlib/server_kit/confined_files.h"

#include <gmock/gmock.h>
#include <gtest/gtest.h>
#include <sys/stat.h>
#include <unistd.h>

#include <cstdlib>
#include <filesystem>
#include <fstream>
#include <string>

#include "behaviorlib/error_details.h"

namespace behaviorlib::server_kit {
namespace {

namespace fs = std::filesystem;
using ::testing::HasSubstr;

class ConfinedFilesTest : public ::testing::Test {
 protected:
  void SetUp() override {
    std::string templ = (fs::temp_directory_path() / "confined-XXXXXX").string();
    ASSERT_NE(::mkdtemp(templ.data()), nullptr);
    base_ = fs::canonical(templ);
    fs::create_directories(base_ / "root" / "sub");
    fs::create_directories(base_ / "outside");
    write(base_ / "root" / "mission.yaml", "name: m\n");
    write(base_ / "root" / "sub" / "deep.yaml", "name: d\n");
    write(base_ / "outside" / "secret", "secret\n");
    auto dir = ConfinedDirectory::open("mission files", (base_ / "root").string(), 64);
    ASSERT_TRUE(dir.ok()) << dir.status();
    dir_ = *dir;
  }
  void TearDown() override { fs::remove_all(base_); }
  static void write(const fs::path& p, const std::string& text) { std::ofstream(p) << text; }

  fs::path base_;
  ConfinedDirectory dir_;
};

TEST_F(ConfinedFilesTest, ReadsRelativeAndAbsolutePathsInside) {
  EXPECT_EQ(*dir_.read("mission.yaml"), "name: m\n");
  EXPECT_EQ(*dir_.read("sub/deep.yaml"), "name: d\n");
  EXPECT_EQ(*dir_.read((base_ / "root" / "sub" / "deep.yaml").string()), "name: d\n");
  // ".." is refused even where it would stay inside.
  EXPECT_EQ(dir_.resolveExisting("./sub/../mission.yaml").status().code(),
            absl::StatusCode::kPermissionDenied);
}

TEST_F(ConfinedFilesTest, RefusesEscapesNamingTheDirectory) {
  for (const std::string& bad :
       {std::string("../outside/secret"), (base_ / "outside" / "secret").string(),
        std::string("/etc/passwd"), std::string("sub/../../outside/secret")}) {
    const auto r = dir_.read(bad);
    EXPECT_EQ(r.status().code(), absl::StatusCode::kPermissionDenied) << bad;
    EXPECT_THAT(r.status().message(), HasSubstr((base_ / "root").string())) << bad;
    // Machine-readable too (errors.proto).
    EXPECT_EQ(errors::reasonOf(r.status()), "PATH_OUTSIDE_ALLOWED_DIRECTORY") << bad;
    EXPECT_EQ(errors::errorInfo(r.status())->metadata().at("path"), bad);
    EXPECT_EQ(errors::errorInfo(r.status())->metadata().at("allowed_directory"),
              (base_ / "root").string());
  }
}

TEST_F(ConfinedFilesTest, RefusesALinkThatLeadsOutside) {
  fs::create_symlink(base_ / "outside" / "secret", base_ / "root" / "link");
  fs::create_directory_symlink(base_ / "outside", base_ / "root" / "dirlink");
  EXPECT_EQ(dir_.read("link").status().code(), absl::StatusCode::kPermissionDenied);
  EXPECT_EQ(dir_.read("dirlink/secret").status().code(), absl::StatusCode::kPermissionDenied);
  EXPECT_EQ(dir_.resolveForWrite("dirlink/new.bt").status().code(),
            absl::StatusCode::kPermissionDenied);
  // Writing through a link that exists, even to inside, is refused.
  fs::create_symlink(base_ / "root" / "mission.yaml", base_ / "root" / "inner");
  EXPECT_EQ(dir_.resolveForWrite("inner").status().code(), absl::StatusCode::kPermissionDenied);
  // A link inside that stays inside is followed for reading.
  EXPECT_EQ(*dir_.read("inner"), "name: m\n");
}

TEST_F(ConfinedFilesTest, CapsReadsAndRefusesDevicesAndDirectories) {
  write(base_ / "root" / "big.yaml", std::string(65, 'x'));
  EXPECT_EQ(dir_.read("big.yaml").status().code(), absl::StatusCode::kResourceExhausted);
  EXPECT_EQ(errors::reasonOf(dir_.read("big.yaml").status()), "FILE_TOO_LARGE");
  EXPECT_EQ(errors::errorInfo(dir_.read("big.yaml").status())->metadata().at("limit"), "64");
  EXPECT_EQ(dir_.read("sub").status().code(), absl::StatusCode::kInvalidArgument);
  EXPECT_EQ(dir_.read("missing.yaml").status().code(), absl::StatusCode::kNotFound);
  EXPECT_EQ(errors::reasonOf(dir_.read("missing.yaml").status()), "FILE_NOT_FOUND");
  auto dev = ConfinedDirectory::open("worlds", "/dev", 64);
  ASSERT_TRUE(dev.ok());
  EXPECT_EQ(dev->read("zero").status().code(), absl::StatusCode::kInvalidArgument);
  EXPECT_EQ(readFileCapped("/dev/zero", 64).status().code(), absl::StatusCode::kInvalidArgument);
  EXPECT_EQ(*readFileCapped((base_ / "outside" / "secret").string(), 64), "secret\n");
}

TEST_F(ConfinedFilesTest, WritesOnlyInExistingDirectoriesInside) {
  auto target = dir_.resolveForWrite("sub/map.bt");
  ASSERT_TRUE(target.ok()) << target.status();
  EXPECT_EQ(*target, (base_ / "root" / "sub" / "map.bt").string());
  EXPECT_EQ(dir_.resolveForWrite("nowhere/map.bt").status().code(), absl::StatusCode::kNotFound);
  EXPECT_EQ(dir_.resolveForWrite("sub").status().code(), absl::StatusCode::kPermissionDenied);
  EXPECT_EQ(dir_.resolveForWrite("../outside/x").status().code(),
            absl::StatusCode::kPermissionDenied);
}

TEST_F(ConfinedFilesTest, WritesByRenamingANewFileOverTheOld) {
  auto written = dir_.write("sub/map.bt", "first");
  ASSERT_TRUE(written.ok()) << written.status();
  EXPECT_EQ(*written, (base_ / "root" / "sub" / "map.bt").string());
  ASSERT_TRUE(dir_.write("sub/map.bt", "second").ok());
  EXPECT_EQ(*dir_.read("sub/map.bt"), "second");
  // No temporary file is left beside it.
  size_t entries = 0;
  for ([[maybe_unused]] const auto& e : fs::directory_iterator(base_ / "root" / "sub")) ++entries;
  EXPECT_EQ(entries, 2u);  // deep.yaml, map.bt

  // A hard link to a file outside looks like a regular file inside: the write
  // replaces the link's name and leaves the outside file alone.
  fs::create_hard_link(base_ / "outside" / "secret", base_ / "root" / "linked");
  ASSERT_TRUE(dir_.write("linked", "map").ok());
  EXPECT_EQ(*readFileCapped((base_ / "outside" / "secret").string(), 64), "secret\n");
  EXPECT_EQ(*dir_.read("linked"), "map");

  // A symbolic link at the file's place is refused; its target is untouched.
  fs::create_symlink(base_ / "outside" / "secret", base_ / "root" / "symlinked");
  const auto refused = dir_.write("symlinked", "map");
  EXPECT_EQ(refused.status().code(), absl::StatusCode::kPermissionDenied);
  EXPECT_THAT(refused.status().message(), HasSubstr((base_ / "root").string()));
  EXPECT_EQ(*readFileCapped((base_ / "outside" / "secret").string(), 64), "secret\n");
  EXPECT_EQ(dir_.write("../outside/secret", "x").status().code(),
            absl::StatusCode::kPermissionDenied);
}

TEST(ConfinedDirectoryTest, WithoutADirectoryEverythingIsRefused) {
  ConfinedDirectory none;
  EXPECT_FALSE(none.enabled());
  const auto r = none.read("/etc/hostname");
  EXPECT_EQ(r.status().code(), absl::StatusCode::kPermissionDenied);
  EXPECT_THAT(r.status().message(), HasSubstr("no directory is configured"));
  EXPECT_EQ(ConfinedDirectory::open("maps", "/does/not/exist", 1).status().code(),
            absl::StatusCode::kInvalidArgument);
}

}  // namespace
}  // namespace behaviorlib::server_kit
