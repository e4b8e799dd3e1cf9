// ThreadSanitizer annotations for Debian's abseil: its mutex and the
// reference count of absl::Status (linked only in
// -DBEHAVIORLIB_SANITIZE=thread builds; see decision 25).
//
// Debian builds libabsl_synchronization without TSan, so TSan does not see an
// absl::Mutex being taken: every field guarded by one would be reported as a
// race. This file defines the out-of-line lock functions of absl::Mutex and
// absl::CondVar in the program itself. The program's definitions take
// precedence over the shared library's, for our code and for gRPC's (which
// locks absl::Mutex too). Each one tells TSan what happens with the
// __tsan_mutex_* annotations that abseil's own TSan build uses, and calls the
// library's function, found with dlsym(RTLD_NEXT).
//
// The library's functions call one another (WaitWithTimeout calls
// WaitWithDeadline) through the same symbols: only the outermost call is
// annotated.
//
// Memory accesses between a pre and a post annotation are ignored by TSan, so
// a Condition evaluated inside the library (by the waiter, or by the thread
// unlocking on its behalf) is not reported; a race that only shows inside a
// Condition's predicate goes unseen in these builds.

#include <dlfcn.h>

#include <cstdio>
#include <cstdlib>
#include <string>

#include "absl/base/options.h"
#include "absl/status/status.h"
#include "absl/synchronization/mutex.h"
#include "absl/time/time.h"

extern "C" {
void __tsan_acquire(void* addr);
void __tsan_release(void* addr);
void __tsan_mutex_pre_lock(void* addr, unsigned flags);
void __tsan_mutex_post_lock(void* addr, unsigned flags, int recursion);
int __tsan_mutex_pre_unlock(void* addr, unsigned flags);
void __tsan_mutex_post_unlock(void* addr, unsigned flags);
}

namespace {

// The flag values of compiler-rt's tsan_interface.h.
constexpr unsigned kReadLock = 1 << 3;
constexpr unsigned kTryLock = 1 << 4;
constexpr unsigned kTryLockFailed = 1 << 5;

#define BEHAVIORLIB_STR2(x) #x
#define BEHAVIORLIB_STR(x) BEHAVIORLIB_STR2(x)

// "_ZN4absl<len><inline namespace>" + the rest of the mangled name.
std::string mangled(const char* rest) {
  const std::string ns = BEHAVIORLIB_STR(ABSL_OPTION_INLINE_NAMESPACE_NAME);
  return "_ZN4absl" + std::to_string(ns.size()) + ns + rest;
}

template <class F>
F next(const char* rest) {
  const std::string name = mangled(rest);
  void* symbol = dlsym(RTLD_NEXT, name.c_str());
  if (symbol == nullptr) {
    std::fprintf(stderr, "tsan_absl_annotations: %s not found in the loaded abseil\n",
                 name.c_str());
    std::abort();
  }
  return reinterpret_cast<F>(symbol);
}

// How deep this thread is in the annotated functions.
thread_local int depth = 0;

struct Outermost {
  Outermost() { ++depth; }
  ~Outermost() { --depth; }
  Outermost(const Outermost&) = delete;
  Outermost& operator=(const Outermost&) = delete;
  static bool nested() { return depth > 0; }
};

using absl::Condition;
using absl::CondVar;
using absl::Duration;
using absl::Mutex;
using absl::Time;

// A lock that may block: announced, taken by the library, then recorded.
template <class R, class... A>
R locking(void* mu, unsigned flags, R (*original)(Mutex*, A...), Mutex* self, A... args) {
  __tsan_mutex_pre_lock(mu, flags);
  if constexpr (std::is_void_v<R>) {
    original(self, args...);
    __tsan_mutex_post_lock(mu, flags, 0);
  } else {
    R result = original(self, args...);
    __tsan_mutex_post_lock(mu, flags, 0);
    return result;
  }
}

void releasing(void* mu, unsigned flags) {
  __tsan_mutex_pre_unlock(mu, flags);
  __tsan_mutex_post_unlock(mu, flags);
}

void acquiring(void* mu, unsigned flags) {
  __tsan_mutex_pre_lock(mu, flags);
  __tsan_mutex_post_lock(mu, flags, 0);
}

}  // namespace

namespace absl {
ABSL_NAMESPACE_BEGIN

void Mutex::Lock() {
  static const auto original = next<void (*)(Mutex*)>("5Mutex4LockEv");
  if (Outermost::nested()) return original(this);
  const Outermost outermost;
  locking(this, 0, original, this);
}

void Mutex::ReaderLock() {
  static const auto original = next<void (*)(Mutex*)>("5Mutex10ReaderLockEv");
  if (Outermost::nested()) return original(this);
  const Outermost outermost;
  locking(this, kReadLock, original, this);
}

bool Mutex::TryLock() {
  static const auto original = next<bool (*)(Mutex*)>("5Mutex7TryLockEv");
  if (Outermost::nested()) return original(this);
  const Outermost outermost;
  __tsan_mutex_pre_lock(this, kTryLock);
  const bool locked = original(this);
  __tsan_mutex_post_lock(this, locked ? kTryLock : kTryLock | kTryLockFailed, 0);
  return locked;
}

bool Mutex::ReaderTryLock() {
  static const auto original = next<bool (*)(Mutex*)>("5Mutex13ReaderTryLockEv");
  if (Outermost::nested()) return original(this);
  const Outermost outermost;
  __tsan_mutex_pre_lock(this, kReadLock | kTryLock);
  const bool locked = original(this);
  __tsan_mutex_post_lock(this,
                         locked ? kReadLock | kTryLock : kReadLock | kTryLock | kTryLockFailed, 0);
  return locked;
}

void Mutex::Unlock() {
  static const auto original = next<void (*)(Mutex*)>("5Mutex6UnlockEv");
  if (Outermost::nested()) return original(this);
  const Outermost outermost;
  __tsan_mutex_pre_unlock(this, 0);
  original(this);
  __tsan_mutex_post_unlock(this, 0);
}

void Mutex::ReaderUnlock() {
  static const auto original = next<void (*)(Mutex*)>("5Mutex12ReaderUnlockEv");
  if (Outermost::nested()) return original(this);
  const Outermost outermost;
  __tsan_mutex_pre_unlock(this, kReadLock);
  original(this);
  __tsan_mutex_post_unlock(this, kReadLock);
}

void Mutex::LockWhen(const Condition& cond) {
  static const auto original =
      next<void (*)(Mutex*, const Condition&)>("5Mutex8LockWhenERKNS0_9ConditionE");
  if (Outermost::nested()) return original(this, cond);
  const Outermost outermost;
  locking<void, const Condition&>(this, 0, original, this, cond);
}

bool Mutex::LockWhenWithTimeout(const Condition& cond, Duration timeout) {
  static const auto original = next<bool (*)(Mutex*, const Condition&, Duration)>(
      "5Mutex19LockWhenWithTimeoutERKNS0_9ConditionENS0_8DurationE");
  if (Outermost::nested()) return original(this, cond, timeout);
  const Outermost outermost;
  return locking<bool, const Condition&, Duration>(this, 0, original, this, cond, timeout);
}

bool Mutex::LockWhenWithDeadline(const Condition& cond, Time deadline) {
  static const auto original = next<bool (*)(Mutex*, const Condition&, Time)>(
      "5Mutex20LockWhenWithDeadlineERKNS0_9ConditionENS0_4TimeE");
  if (Outermost::nested()) return original(this, cond, deadline);
  const Outermost outermost;
  return locking<bool, const Condition&, Time>(this, 0, original, this, cond, deadline);
}

void Mutex::ReaderLockWhen(const Condition& cond) {
  static const auto original =
      next<void (*)(Mutex*, const Condition&)>("5Mutex14ReaderLockWhenERKNS0_9ConditionE");
  if (Outermost::nested()) return original(this, cond);
  const Outermost outermost;
  locking<void, const Condition&>(this, kReadLock, original, this, cond);
}

// Await and CondVar::Wait may give the lock up and take it back: for TSan
// the caller releases it before and acquires it after (from whoever held it
// last), with the library's work in between ignored.
void Mutex::Await(const Condition& cond) {
  static const auto original =
      next<void (*)(Mutex*, const Condition&)>("5Mutex5AwaitERKNS0_9ConditionE");
  if (Outermost::nested()) return original(this, cond);
  const Outermost outermost;
  __tsan_mutex_pre_unlock(this, 0);
  original(this, cond);
  __tsan_mutex_post_unlock(this, 0);
  acquiring(this, 0);
}

bool Mutex::AwaitWithTimeout(const Condition& cond, Duration timeout) {
  static const auto original = next<bool (*)(Mutex*, const Condition&, Duration)>(
      "5Mutex16AwaitWithTimeoutERKNS0_9ConditionENS0_8DurationE");
  if (Outermost::nested()) return original(this, cond, timeout);
  const Outermost outermost;
  __tsan_mutex_pre_unlock(this, 0);
  const bool result = original(this, cond, timeout);
  __tsan_mutex_post_unlock(this, 0);
  acquiring(this, 0);
  return result;
}

bool Mutex::AwaitWithDeadline(const Condition& cond, Time deadline) {
  static const auto original = next<bool (*)(Mutex*, const Condition&, Time)>(
      "5Mutex17AwaitWithDeadlineERKNS0_9ConditionENS0_4TimeE");
  if (Outermost::nested()) return original(this, cond, deadline);
  const Outermost outermost;
  __tsan_mutex_pre_unlock(this, 0);
  const bool result = original(this, cond, deadline);
  __tsan_mutex_post_unlock(this, 0);
  acquiring(this, 0);
  return result;
}

void CondVar::Wait(Mutex* mu) {
  static const auto original = next<void (*)(CondVar*, Mutex*)>("7CondVar4WaitEPNS0_5MutexE");
  if (Outermost::nested()) return original(this, mu);
  const Outermost outermost;
  releasing(mu, 0);
  original(this, mu);
  acquiring(mu, 0);
}

bool CondVar::WaitWithTimeout(Mutex* mu, Duration timeout) {
  static const auto original = next<bool (*)(CondVar*, Mutex*, Duration)>(
      "7CondVar15WaitWithTimeoutEPNS0_5MutexENS0_8DurationE");
  if (Outermost::nested()) return original(this, mu, timeout);
  const Outermost outermost;
  releasing(mu, 0);
  const bool result = original(this, mu, timeout);
  acquiring(mu, 0);
  return result;
}

bool CondVar::WaitWithDeadline(Mutex* mu, Time deadline) {
  static const auto original =
      next<bool (*)(CondVar*, Mutex*, Time)>("7CondVar16WaitWithDeadlineEPNS0_5MutexENS0_4TimeE");
  if (Outermost::nested()) return original(this, mu, deadline);
  const Outermost outermost;
  releasing(mu, 0);
  const bool result = original(this, mu, deadline);
  acquiring(mu, 0);
  return result;
}

// absl::Status shares its heap representation between copies and counts
// references with atomics inside libabsl_status. Every drop of a reference
// releases, and acquires what the others released, so the thread that frees
// the representation comes after every thread that read it.
void Status::UnrefNonInlined(uintptr_t rep) {
  static const auto original = next<void (*)(uintptr_t)>("6Status15UnrefNonInlinedEm");
  __tsan_release(reinterpret_cast<void*>(rep));
  __tsan_acquire(reinterpret_cast<void*>(rep));
  original(rep);
}

ABSL_NAMESPACE_END
}  // namespace absl
