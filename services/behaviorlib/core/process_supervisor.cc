#include "behaviorlib/process_supervisor.h"

#include <signal.h>
#include <sys/wait.h>
#include <unistd.h>

#include <thread>

namespace behaviorlib {

ChildProcess::ChildProcess(std::vector<std::string> argv) : argv_(std::move(argv)) {}

ChildProcess::~ChildProcess() { stop(); }

absl::Status ChildProcess::start() {
  if (argv_.empty()) return absl::InvalidArgumentError("no program given");
  if (running()) {
    return absl::FailedPreconditionError(argv_[0] + " is already running (pid " +
                                         std::to_string(pid_) + ")");
  }
  std::vector<char*> args;
  for (auto& a : argv_) args.push_back(a.data());
  args.push_back(nullptr);
  exit_description_.clear();
  pid_ = fork();
  if (pid_ < 0) return absl::InternalError("cannot fork to start " + argv_[0]);
  if (pid_ == 0) {
    execvp(args[0], args.data());
    _exit(127);
  }
  return absl::OkStatus();
}

bool ChildProcess::reap(bool block) {
  if (pid_ <= 0) return true;
  int status = 0;
  const pid_t r = waitpid(pid_, &status, block ? 0 : WNOHANG);
  if (r == 0) return false;
  if (r == pid_) {
    if (WIFEXITED(status)) {
      const int code = WEXITSTATUS(status);
      exit_description_ = argv_[0] + (code == 127 ? " could not be started or exited with code 127"
                                                  : " exited with code " + std::to_string(code));
    } else if (WIFSIGNALED(status)) {
      exit_description_ = argv_[0] + " was killed by signal " + std::to_string(WTERMSIG(status));
    }
  } else {
    exit_description_ = argv_[0] + " is gone (waitpid failed)";
  }
  pid_ = -1;
  return true;
}

bool ChildProcess::running() { return pid_ > 0 && !reap(false); }

Verdict ChildProcess::check() {
  if (running()) return Verdict::keepGoing();
  return Verdict::finish(exit_description_.empty() ? argv_[0] + " is not running"
                                                   : exit_description_);
}

void ChildProcess::stop(std::chrono::milliseconds grace) {
  if (pid_ <= 0) return;
  kill(pid_, SIGTERM);
  const auto deadline = std::chrono::steady_clock::now() + grace;
  while (std::chrono::steady_clock::now() < deadline) {
    if (reap(false)) return;
    std::this_thread::sleep_for(std::chrono::milliseconds(2));
  }
  kill(pid_, SIGKILL);
  reap(true);
}

SupervisedThread::SupervisedThread(Body body, std::chrono::milliseconds max_silence)
    : max_silence_(max_silence) {
  thread_ = std::thread([this, body = std::move(body)] {
    std::string failure;
    try {
      body(stop_, heartbeat_);
      if (!stop_.load()) failure = "worker thread returned unexpectedly";
    } catch (const std::exception& e) {
      failure = std::string("worker thread threw: ") + e.what();
    } catch (...) {
      failure = "worker thread threw a non-standard exception";
    }
    {
      absl::MutexLock lock(&mutex_);
      failure_ = failure;
    }
    exited_.store(true);
  });
}

SupervisedThread::~SupervisedThread() { stop(); }

void SupervisedThread::stop() {
  stop_.store(true);
  if (thread_.joinable()) thread_.join();
}

Verdict SupervisedThread::check() const {
  if (exited_.load()) {
    absl::MutexLock lock(&mutex_);
    return Verdict::finish(failure_.empty() ? "worker thread stopped" : failure_);
  }
  const auto silence = std::chrono::steady_clock::now() - heartbeat_.last();
  if (silence > max_silence_) {
    return Verdict::finish(
        "worker thread silent for " +
        std::to_string(std::chrono::duration_cast<std::chrono::milliseconds>(silence).count()) +
        " ms (limit " + std::to_string(max_silence_.count()) + " ms)");
  }
  return Verdict::keepGoing();
}

}  // namespace behaviorlib
