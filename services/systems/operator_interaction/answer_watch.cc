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
    absl::MutexLock lock(&mutex_);
    stopping_ = true;
  }
  if (thread_.joinable()) thread_.join();
}

AnswerWatch::State AnswerWatch::state() const {
  absl::MutexLock lock(&mutex_);
  return state_;
}

std::optional<v1::Belief> AnswerWatch::answer() const {
  absl::MutexLock lock(&mutex_);
  return answer_;
}

std::optional<std::string> AnswerWatch::failure() const {
  absl::MutexLock lock(&mutex_);
  return failure_;
}

uint64_t AnswerWatch::questionVersion() const {
  absl::MutexLock lock(&mutex_);
  return question_version_;
}

bool AnswerWatch::record(const absl::Status& status) {
  absl::MutexLock lock(&mutex_);
  if (status.ok()) {
    failure_.reset();
    return true;
  }
  if (!failure_) failure_ = std::string(status.message());
  return false;
}

bool AnswerWatch::pause(std::chrono::milliseconds period) {
  absl::MutexLock lock(&mutex_);
  return mutex_.AwaitWithTimeout(absl::Condition(&stopping_), absl::FromChrono(period));
}

void AnswerWatch::run() {
  // 1. The question.
  uint64_t asked = 0;
  for (;;) {
    auto written = beliefs_.write(request_.request_key, request_.question, request_.writer);
    if (record(written.status())) {
      asked = written->version();
      absl::MutexLock lock(&mutex_);
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
  absl::MutexLock lock(&mutex_);
  answer_ = answer;
  state_ = State::kAnswered;
}

}  // namespace behaviorlib::operator_interaction
