#include "behaviorlib/operator_interaction/answer_watch.h"

namespace behaviorlib::operator_interaction {

AnswerWatch::AnswerWatch(const server::BeliefClient& beliefs, Request request)
    : beliefs_(beliefs), request_(std::move(request)) {}

AnswerWatch::~AnswerWatch() { stop(); }

void AnswerWatch::start() {
  if (!thread_.joinable()) thread_ = std::thread([this] { run(); });
}

void AnswerWatch::stop() {
  {
    std::lock_guard lock(mutex_);
    stopping_ = true;
    wake_.notify_all();
  }
  if (thread_.joinable()) thread_.join();
}

AnswerWatch::State AnswerWatch::state() const {
  std::lock_guard lock(mutex_);
  return state_;
}

std::optional<v1::Belief> AnswerWatch::answer() const {
  std::lock_guard lock(mutex_);
  return answer_;
}

std::optional<std::string> AnswerWatch::failure() const {
  std::lock_guard lock(mutex_);
  return failure_;
}

uint64_t AnswerWatch::questionVersion() const {
  std::lock_guard lock(mutex_);
  return question_version_;
}

bool AnswerWatch::record(const absl::Status& status) {
  std::lock_guard lock(mutex_);
  if (status.ok()) {
    failure_.reset();
    return true;
  }
  if (!failure_) failure_ = std::string(status.message());
  return false;
}

bool AnswerWatch::pause(std::chrono::milliseconds period) {
  std::unique_lock lock(mutex_);
  return wake_.wait_for(lock, period, [&] { return stopping_; });
}

void AnswerWatch::run() {
  // 1. The question.
  uint64_t asked = 0;
  for (;;) {
    auto written = beliefs_.write(request_.request_key, request_.question, request_.writer);
    if (record(written.status())) {
      asked = written->version();
      std::lock_guard lock(mutex_);
      question_version_ = asked;
      state_ = State::kWaiting;
      break;
    }
    if (pause(request_.poll_period)) return;
  }
  // 2. An answer written after the question (an older one answers an
  // earlier request with the same id).
  v1::Belief answer;
  for (;;) {
    if (pause(request_.poll_period)) return;
    auto read = beliefs_.read(request_.answer_key);
    if (read.ok()) {
      record(absl::OkStatus());
      if (!read->deleted() && read->version() > asked) {
        answer = *read;
        break;
      }
    } else if (read.status().code() == absl::StatusCode::kNotFound) {
      record(absl::OkStatus());
    } else {
      record(read.status());
    }
  }
  // 3. The copy where the mission reads it.
  for (;;) {
    auto copied = beliefs_.write(request_.copy_key, answer.value(), request_.writer, answer.type());
    if (record(copied.status())) break;
    if (pause(request_.poll_period)) return;
  }
  std::lock_guard lock(mutex_);
  answer_ = answer;
  state_ = State::kAnswered;
}

}  // namespace behaviorlib::operator_interaction
