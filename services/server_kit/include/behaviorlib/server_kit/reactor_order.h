#pragma once

// The order of a gRPC callback reactor's steps, made visible to
// ThreadSanitizer (decision 25).
//
// gRPC runs a reactor's callbacks one after another, but on whichever thread
// its completion queue picks, and it hands the call from thread to thread
// through lock-free queues inside Debian's libgrpc, which is not built with
// TSan. So TSan sees no order between what our code does before a StartWrite
// (or StartRead, Finish, ...) and what the callback that follows does: each
// such pair would be reported as a race.
//
// Ordered<Reactor> tells TSan that order. Its Start* and Finish release the
// reactor; each callback we override begins with `ordered()`, which acquires
// it:
//
//   class Feed final : public server_kit::Ordered<grpc::ServerWriteReactor<v1::Sample>> {
//     void OnWriteDone(bool ok) override {
//       ordered();
//       ...
//       StartWrite(&next_);   // released here, acquired by the next OnWriteDone
//     }
//   };
//
// Outside TSan builds both are nothing. Accesses that are not ordered by
// these steps (two threads touching a reactor's field with no lock) are still
// reported.

#include <memory>
#include <utility>

#if defined(__SANITIZE_THREAD__)
#define BEHAVIORLIB_TSAN_ORDER 1
#elif defined(__has_feature)
#if __has_feature(thread_sanitizer)
#define BEHAVIORLIB_TSAN_ORDER 1
#endif
#endif

#ifdef BEHAVIORLIB_TSAN_ORDER
extern "C" void __tsan_acquire(void* addr);
extern "C" void __tsan_release(void* addr);
#endif

namespace behaviorlib::server_kit {

/// For a callback that gRPC runs on one of its threads, such as a client's
/// unary completion: happensBefore(key) just before the call starts, and
/// happensAfter(key) first in the callback, with the same key (the call's
/// state).
inline void happensBefore([[maybe_unused]] const void* key) {
#ifdef BEHAVIORLIB_TSAN_ORDER
  __tsan_release(const_cast<void*>(key));
#endif
}
inline void happensAfter([[maybe_unused]] const void* key) {
#ifdef BEHAVIORLIB_TSAN_ORDER
  __tsan_acquire(const_cast<void*>(key));
#endif
}

#ifdef BEHAVIORLIB_TSAN_ORDER
#define BEHAVIORLIB_NO_TSAN __attribute__((no_sanitize("thread")))
#else
#define BEHAVIORLIB_NO_TSAN
#endif

/// The callback of a client call made with gRPC's callback API
/// (stub->async()->Method(context, &request, &response, orderedCallback(f))),
/// ordered after the call's start for TSan. gRPC copies the callable it is
/// given into its call object and runs it on one of its threads; a lambda's
/// captures read there would race, for TSan, with gRPC's copy. So `f` is kept
/// in an object of ours, released before the call, and the callable gRPC
/// copies holds only its address, which an uninstrumented trampoline reads.
template <class F>
class OrderedCallback {
 public:
  explicit OrderedCallback(F f) : f_(std::move(f)) {}
  template <class Status>
  static void run(OrderedCallback* self, Status status) {
    happensAfter(self);
    std::unique_ptr<OrderedCallback> owned(self);
    owned->f_(std::move(status));
  }

 private:
  F f_;
};

template <class F>
auto orderedCallback(F f) {
  auto* box = new OrderedCallback<F>(std::move(f));
  happensBefore(box);
  return [box](auto status)
             BEHAVIORLIB_NO_TSAN { OrderedCallback<F>::run(box, std::move(status)); };
}

template <class Reactor>
class Ordered : public Reactor {
 public:
  using Reactor::Reactor;

  // These hide the reactor's own functions of the same names, and call them.
  template <class... A>
  void StartWrite(A&&... a) {
    release();
    Reactor::StartWrite(std::forward<A>(a)...);
  }
  template <class... A>
  void StartWriteLast(A&&... a) {
    release();
    Reactor::StartWriteLast(std::forward<A>(a)...);
  }
  template <class... A>
  void StartWriteAndFinish(A&&... a) {
    release();
    Reactor::StartWriteAndFinish(std::forward<A>(a)...);
  }
  template <class... A>
  void StartRead(A&&... a) {
    release();
    Reactor::StartRead(std::forward<A>(a)...);
  }
  template <class... A>
  void Finish(A&&... a) {
    release();
    Reactor::Finish(std::forward<A>(a)...);
  }
  template <class... A>
  void StartSendInitialMetadata(A&&... a) {
    release();
    Reactor::StartSendInitialMetadata(std::forward<A>(a)...);
  }
  template <class... A>
  void StartCall(A&&... a) {
    release();
    Reactor::StartCall(std::forward<A>(a)...);
  }
  template <class... A>
  void StartWritesDone(A&&... a) {
    release();
    Reactor::StartWritesDone(std::forward<A>(a)...);
  }
  template <class... A>
  void RemoveHold(A&&... a) {
    release();
    Reactor::RemoveHold(std::forward<A>(a)...);
  }

 protected:
  /// First in every callback the reactor overrides (OnReadDone, OnWriteDone,
  /// OnDone, OnCancel, OnReadInitialMetadataDone, ...). It acquires what the
  /// steps before released, and releases what gRPC did on this thread before
  /// calling us (reading the callback's tag), so that OnDone, which deletes
  /// the reactor and gRPC's call object after it, is ordered after it.
  void ordered() {
    happensAfter(this);
    happensBefore(this);
  }

 private:
  void release() { happensBefore(this); }
};

}  // namespace behaviorlib::server_kit
