# One image for every role; docker-compose.yml picks the role with `neso run <role>`.
FROM python:3.11-slim
WORKDIR /app
RUN pip install --no-cache-dir torch==2.13.0 --index-url https://download.pytorch.org/whl/cpu
COPY pyproject.toml README.md ./
COPY neso neso
COPY sim sim
COPY runtime runtime
COPY flight flight
COPY services services
COPY dashboard dashboard
COPY recordings recordings
COPY cli cli
RUN pip install --no-cache-dir .
COPY networks /data/networks
ENTRYPOINT ["neso"]
