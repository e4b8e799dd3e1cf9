#pragma once

// Files a request may name, confined to a directory configured for that
// purpose (the coordinator's missions, the simulator's worlds, the maps a
// navigation system saves).
//
// A requested path, relative to the directory or absolute, is accepted only
// if it has no ".." component and, once every symbolic link is resolved, lies
// inside the directory. Reads are of regular files only and capped in size
// (a path such as /dev/zero can be neither). Errors name the directory:
//
//   ConfinedDirectory missions("mission files", "/opt/behaviorlib/missions", 1 << 20);
//   absl::StatusOr<std::string> text = missions.read(request.file_path());
//   // PERMISSION_DENIED "mission files must be inside /opt/behaviorlib/missions: ..."
//
// What is not covered: a process that may change the directory's contents
// between the check and the open can swap a directory of the path for a link
// (the directory should be writable only by the process that uses it, or by
// nobody). A link at the file's own place is not followed: reads open it
// with O_NOFOLLOW, and write() renames a new file over it.

#include <cstddef>
#include <string>
#include <string_view>

#include "absl/status/status.h"
#include "absl/status/statusor.h"

namespace behaviorlib::server_kit {

class ConfinedDirectory {
 public:
  /// `purpose` names the files in errors ("mission files"). An empty `root`
  /// refuses every path (the feature is off); otherwise it must exist.
  static absl::StatusOr<ConfinedDirectory> open(std::string purpose, const std::string& root,
                                                size_t max_read_bytes);
  /// A directory that refuses every path.
  ConfinedDirectory() = default;

  bool enabled() const { return !root_.empty(); }
  const std::string& root() const { return root_; }
  size_t maxReadBytes() const { return max_read_bytes_; }

  /// The absolute, link-free path of an existing file inside the directory.
  absl::StatusOr<std::string> resolveExisting(const std::string& requested) const;
  /// The absolute path at which a file may be written: its parent directory
  /// exists inside the directory, and the file, if it exists, is a regular
  /// file and not a link.
  absl::StatusOr<std::string> resolveForWrite(const std::string& requested) const;
  /// Writes `contents` to the file resolveForWrite() gives, atomically: to a
  /// new file beside it (made with O_EXCL and O_NOFOLLOW, so no link is
  /// followed), then renamed over it, which replaces a link put at its place
  /// since the check rather than following it. Returns the path written.
  absl::StatusOr<std::string> write(const std::string& requested, std::string_view contents) const;
  /// The contents of a regular file inside the directory, at most
  /// maxReadBytes() long (RESOURCE_EXHAUSTED beyond).
  absl::StatusOr<std::string> read(const std::string& requested) const;

 private:
  ConfinedDirectory(std::string purpose, std::string root, size_t max_read_bytes)
      : purpose_(std::move(purpose)), root_(std::move(root)), max_read_bytes_(max_read_bytes) {}
  absl::Status refuse(const std::string& requested, const std::string& why) const;
  absl::StatusOr<std::string> lexical(const std::string& requested) const;
  bool inside(const std::string& resolved) const;

  std::string purpose_ = "files";
  std::string root_;
  size_t max_read_bytes_ = 0;
};

/// Reads a file named by configuration (not by a request), refusing anything
/// but a regular file of at most `max_bytes`.
absl::StatusOr<std::string> readFileCapped(const std::string& path, size_t max_bytes);

}  // namespace behaviorlib::server_kit
